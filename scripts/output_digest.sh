#!/usr/bin/env bash
# Runs the standard commands of README.md's tour on fixed seeds with the freefall binary given as
# $1, writing into $2, and prints one SHA-256 digest per output table (values and column names,
# without the run-dependent metadata: version, command line, timings). Two builds whose printed
# digests agree write the same tables. Used to check that a refactoring changes no output:
#   scripts/output_digest.sh target/release/freefall /tmp/digest > after.txt; diff before.txt after.txt
set -euo pipefail
bin=$(realpath "$1"); out=$2
rm -rf "$out"; mkdir -p "$out"; cd "$out"
q="--quiet"
exec 3>&1 >commands.log   # the commands' own printing (timings vary) stays out of the digests
"$bin" $q simulate --scenario monte_carlo --seed 3 --out ds
"$bin" $q simulate --scenario monte_carlo --seed 5 --engine time-domain --out ds_td
"$bin" $q simulate --scenario monte_carlo --seed 2 --effect actuation_lag_df=0.3 --out ds_lag
"$bin" $q simulate --model lpf_xy --scenario crosstalk --seed 4 --out ds_xy
"$bin" $q fit ds/dataset.toml --out fit
"$bin" $q fit ds_td/dataset.toml --out fit_td
"$bin" $q model transfer --model lpf_xy --out transfer_xy.parquet
"$bin" $q fit ds/dataset.toml --transient --out fit_tr
"$bin" $q diagnose ds_lag/dataset.toml --out diag_lag
"$bin" $q diagnose ds/dataset.toml --out diag
"$bin" $q accel ds/dataset.toml --scenario monte_carlo --use truth --out accel
"$bin" $q campaign run --out camp --threads 2
"$bin" $q design optimize --criterion d --out design
"$bin" $q model transfer --out transfer.parquet
"$bin" $q model noise --out noise.parquet
"$bin" $q model fisher --scenario monte_carlo --out fisher.parquet
"$bin" $q psd ds/noise.parquet --out psd.parquet
exec 1>&3
python3 - <<'PY'
import hashlib, json, pathlib, re, pyarrow.parquet as pq
# the build's version string ("0.1.0 (COMMIT, PROFILE)") is run-dependent metadata too
VERSION = re.compile(rb'\d+\.\d+\.\d+ \([0-9a-f]+(-dirty)?, \w+\)')
for p in sorted(pathlib.Path('.').rglob('*')):
    if p.suffix == '.parquet':
        t = pq.read_table(p)
        h = hashlib.sha256()
        for name in t.column_names:
            if name == 'seconds':   # a realization's wall time
                continue
            h.update(name.encode())
            h.update(repr(t.column(name).to_pylist()).encode())
        print(f"{h.hexdigest()[:16]}  {p}")
    elif p.suffix == '.json' and p.name in ('fit.json', 'report.json', 'manifest.json'):
        d = json.loads(p.read_text())
        def strip(x):
            if isinstance(x, dict):
                return {k: strip(v) for k, v in x.items()
                        if k not in ('seconds', 'provenance', 'version', 'elapsed_s', 'wall_s', 'created', 'command', 'started', 'finished', 'threads', 'host', 'started_unix', 'finished_unix', 'wall_seconds', 'fit_seconds', 'realizations_per_second')}
            if isinstance(x, list):
                return [strip(v) for v in x]
            return x
        print(f"{hashlib.sha256(VERSION.sub(b'VERSION', json.dumps(strip(d), sort_keys=True).encode())).hexdigest()[:16]}  {p}")
    elif p.suffix in ('.toml', '.csv', '.md') and 'plots' not in p.parts:
        print(f"{hashlib.sha256(VERSION.sub(b'VERSION', p.read_bytes())).hexdigest()[:16]}  {p}")
PY
