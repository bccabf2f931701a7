#!/usr/bin/env bash
# Interleaved A/B timing of two freefall binaries (e.g. a release build of an older commit and
# the current one) on the same inputs: a 1000-realization campaign and a diagnosis of the
# loss-angle example, ROUNDS rounds each, old and new alternating so that machine drift hits
# both alike. Usage: scripts/ab_bench.sh OLD_BINARY NEW_BINARY [ROUNDS]
set -euo pipefail
OLD=$(realpath "$1"); NEW=$(realpath "$2"); ROUNDS=${3:-3}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
cd "$WORK"
"$NEW" simulate --effect loss_angle_tm2=0.01 --seed 3 --noise-duration 10800 --out lossy -q
now() { date +%s.%N; }
for i in $(seq 1 "$ROUNDS"); do
  for tag in old new; do
    BIN=$OLD; [ "$tag" = new ] && BIN=$NEW
    rm -rf "mc_$tag" "d_$tag"
    t0=$(now)
    "$BIN" campaign run "$ROOT/campaigns/monte_carlo.toml" --out "mc_$tag" --threads 2 -q >/dev/null
    t1=$(now)
    "$BIN" diagnose lossy/dataset.toml --out "d_$tag" --no-plots -q > "d_$tag.txt"
    t2=$(now)
    printf '%s round %d: campaign %.2f s; diagnose %.2f s; %s\n' "$tag" "$i" \
      "$(echo "$t1 - $t0" | bc)" "$(echo "$t2 - $t1" | bc)" "$(tail -1 "d_$tag.txt")"
  done
done
