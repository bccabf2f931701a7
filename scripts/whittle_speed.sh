#!/usr/bin/env bash
# The Whittle campaign path against the NumPy/SciPy peer (scripts/peer_fit.py), in one sitting:
# `freefall campaign run` of campaigns/monte_carlo.toml with `[fit] likelihood = "whittle"` and
# REALIZATIONS realizations on THREADS threads (wall, user+system CPU and peak RSS from
# /usr/bin/time), then the peer on PEER_REALIZATIONS realizations on one core; prints core-ms
# per realization for both and their ratio.
# Usage: scripts/whittle_speed.sh FREEFALL_BINARY [REALIZATIONS=10000] [THREADS=2] [PEER_REALIZATIONS=4]
set -euo pipefail
BIN=$(realpath "$1"); N=${2:-10000}; THREADS=${3:-2}; PEER_N=${4:-4}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
sed -e "s|^realizations = .*|realizations = $N|" \
    -e "s|^model = \"models/|model = \"$ROOT/campaigns/models/|" \
    "$ROOT/campaigns/monte_carlo.toml" > "$WORK/mc.toml"
printf '\n[fit]\nlikelihood = "whittle"\n' >> "$WORK/mc.toml"
/usr/bin/time -f '%e %U %S %M' -o "$WORK/time" \
  "$BIN" campaign run "$WORK/mc.toml" --out "$WORK/out" --threads "$THREADS" -q >/dev/null
read -r wall user sys rss < "$WORK/time"
ff=$(echo "($user + $sys) * 1000 / $N" | bc -l)
printf 'freefall whittle: %d realizations, %.1f s wall on %d threads, %.1f s CPU, %.3f core-ms per realization, peak RSS %d MB\n' \
  "$N" "$wall" "$THREADS" "$(echo "$user + $sys" | bc -l)" "$ff" "$((rss / 1024))"
peer=$(OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \
  python3 "$ROOT/scripts/peer_fit.py" --realizations "$PEER_N" | tail -1)
echo "$peer"
peer_ms=$(echo "$peer" | sed -E 's/.*median ([0-9.]+) s per realization.*/\1/')
printf 'ratio peer / freefall: %.0fx (%.1f ms vs %.3f ms per realization and core)\n' \
  "$(echo "$peer_ms * 1000 / $ff" | bc -l)" "$(echo "$peer_ms * 1000" | bc -l)" "$ff"
