#!/usr/bin/env python3
"""Plots of optimal injection designs (thesis ch. 5).

    python3 scripts/plot_design.py DESIGN_DIR [--out DIR]

DESIGN_DIR is the output folder of `freefall design optimize --out DIR` or of
`freefall design validate campaigns/optimal_design.toml`. Figures go to DESIGN_DIR/plots/ unless
--out DIR is given (the convention of every scripts/plot_*.py):

- signals_<design>.png: injections and readouts of each design (thesis fig. "synthetic data
  for optimal design"): one realization at the truth, per experiment;
- limits.png: largest allowed amplitude per constraint vs frequency for oi1 and oi12 (thesis
  figs. "maximum allowed amplitude"), the grid limit f_max marked;
- derivatives.png: normalised directional derivatives of the approximate design (the
  equivalence-theorem plot; the approximate design's support, circled, sits at the maxima);
- landscape_<design>.png: the criterion with two stretches moved over the grid (a 2-D slice of
  the criterion landscape through the optimum), the optimum marked.
Units come from the tables (Parquet field metadata "unit", key-value "freefall.units"); a table
without them is read in the units freefall writes (t in s, signals and amplitudes in m, f in Hz).
Needs numpy, matplotlib and pyarrow.
"""
import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

DPI = 100
# The units freefall writes, for tables written before they carried them.
DEFAULT_UNITS = {"t": "s", "oi1": "m", "oi12": "m", "o1": "m", "o12": "m", "f_hz": "Hz", "a_max_m": "m"}
# Display scale per unit: (factor, label).
SCALE = {"m": (1e6, "um"), "s": (1 / 3600, "h"), "Hz": (1e3, "mHz")}


def column_units(table):
    """Units per column: key-value metadata "freefall.units" (JSON), then field metadata "unit"."""
    units = dict(DEFAULT_UNITS)
    raw = (table.schema.metadata or {}).get(b"freefall.units")
    if raw:
        try:
            units.update(json.loads(raw))
        except ValueError:
            pass
    for f in table.schema:
        if f.metadata and b"unit" in f.metadata:
            units[f.name] = f.metadata[b"unit"].decode()
    return units


def read(path):
    t = pq.read_table(path)
    return t.to_pydict(), column_units(t)


def scaled(units, col):
    """(factor, display unit) for a column: metres in um, seconds in h, Hz in mHz."""
    u = units.get(col, "1")
    if col.startswith("a_max_"):
        u = units.get(col, "m")
    return SCALE.get(u, (1.0, u))


def safe(name):
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def legend_right(ax, **kw):
    """A legend right of the axes: it never covers a trace."""
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False, **kw)


def plot_signals(inp, out):
    path = inp / "signals.parquet"
    if not path.exists():
        return []
    t, units = read(path)
    ids = list(dict.fromkeys(t["design_id"]))
    did = np.array(t["design_id"])
    exp = np.array(t["experiment"])
    cols = {k: np.array(t[k], dtype=float) for k in ("t", "oi1", "oi12", "o1", "o12")}
    ft, ut = scaled(units, "t")
    written = []
    for d in ids:
        exps = list(dict.fromkeys(exp[did == d]))
        fig, axes = plt.subplots(2, len(exps), figsize=(5.5 * len(exps) + 1.8, 5.6), sharex=True, squeeze=False)
        for j, e in enumerate(exps):
            sel = (did == d) & (exp == e)
            th = cols["t"][sel] * ft
            for row, (names, what) in enumerate(((("oi1", "oi12"), "injected guidance"), (("o1", "o12"), "readout"))):
                ax = axes[row][j]
                fy, uy = scaled(units, names[0])
                for k, n in enumerate(names):
                    ax.plot(th, cols[n][sel] * fy, lw=0.6, color=f"C{k}", label=n)
                ax.set_title(f"{d}: {e}, {what}", fontsize=9)
                ax.set_ylabel(f"{what} [{uy}]", fontsize=8)
                ax.tick_params(labelsize=7)
                ax.grid(True, alpha=0.3)
                if j == len(exps) - 1:
                    legend_right(ax)
            axes[1][j].set_xlabel(f"t [{ut}]", fontsize=8)
        fig.tight_layout()
        written.append(out / f"signals_{safe(d)}.png")
        fig.savefig(written[-1], dpi=DPI)
        plt.close(fig)
    return written


def plot_limits(inp, out):
    path = inp / "limits.parquet"
    if not path.exists():
        return []
    t, units = read(path)
    inputs = np.array(t["input"])
    ff, uf = scaled(units, "f_hz")
    fa, ua = scaled(units, "a_max_m")
    f = np.array(t["f_hz"], dtype=float)
    allowed = np.array(t["allowed"], dtype=bool)
    names = [k for k in t if k.startswith("a_max_") and k != "a_max_m"]
    ins = list(dict.fromkeys(inputs))
    fig, axes = plt.subplots(1, len(ins), figsize=(5.2 * len(ins) + 2.2, 4.4), squeeze=False)
    for j, i in enumerate(ins):
        ax = axes[0][j]
        sel = inputs == i
        for k, n in enumerate(names):
            ax.loglog(f[sel] * ff, np.array(t[n], dtype=float)[sel] * fa, color=f"C{k}", lw=1.2,
                      label=n.replace("a_max_", "").replace("_", " "))
        ax.loglog(f[sel] * ff, np.array(t["a_max_m"], dtype=float)[sel] * fa, "k--", lw=2, label="combined (min)")
        if (sel & allowed).any():
            ax.axvline(f[sel & allowed].max() * ff, color="grey", ls=":", lw=1.5, label="f_max (grid limit)")
        ax.set_title(f"largest allowed amplitude, {i}", fontsize=10)
        ax.set_xlabel(f"f [{uf}]")
        ax.set_ylabel(f"a_max [{ua}]")
        ax.grid(True, which="both", alpha=0.25)
    legend_right(axes[0][-1])
    fig.tight_layout()
    fig.savefig(out / "limits.png", dpi=DPI)
    plt.close(fig)
    return [out / "limits.png"]


def plot_derivatives(inp, out):
    path = inp / "derivatives.parquet"
    if not path.exists():
        return []
    t, _ = read(path)
    did = np.array(t["design_id"])
    exp = np.array(t["experiment"])
    c0 = np.array(t["cycles_oi1"])
    c1 = np.array(t["cycles_oi12"])
    d = np.array(t["normalized_derivative"], dtype=float)
    w = np.array(t["approximate_count"], dtype=float)
    ids = list(dict.fromkeys(did))
    fig, axes = plt.subplots(len(ids), 1, figsize=(10, 2.2 * len(ids) + 0.4), sharex=True, squeeze=False)
    for k, i in enumerate(ids):
        ax = axes[k][0]
        maxima = []
        for j, e in enumerate(dict.fromkeys(exp[did == i])):
            sel = (did == i) & (exp == e)
            if np.all(c0[sel] > 0) and np.all(c1[sel] > 0):
                # Simultaneous layout: the best pair per oi1 cycle count.
                x = c0[sel]
                xs = np.unique(x)
                ys = np.array([d[sel][x == v].max() for v in xs])
                ws = np.array([w[sel][x == v].sum() for v in xs])
                label = f"{e} (max over oi12)"
            else:
                xs = np.where(c0[sel] > 0, c0[sel], c1[sel])
                ys, ws = d[sel], w[sel]
                label = f"{e} ({'oi1' if np.all(c0[sel] > 0) else 'oi12'})"
            ax.plot(xs, ys, ".-", ms=3, color=f"C{j}", label=label)
            # The approximate design's support (candidates holding at least 5 % of a slot).
            sup = ws > 0.05
            ax.plot(xs[sup], ys[sup], "o", ms=7, mfc="none", mec=f"C{j}", mew=1.5,
                    label=f"{e}: support of the approximate design")
            maxima.append(float(ys.max()))
        total = " + ".join(f"{m:.2f}" for m in maxima) + (f" = {sum(maxima):.2f}" if len(maxima) > 1 else "")
        ax.set_title(f"{i}: {'sum of the experiments maxima' if len(maxima) > 1 else 'maximum'} {total} "
                     "(1 at the optimum of a smooth criterion)", fontsize=9, loc="left")
        ax.set_ylabel("N_g tr(G M_i) / phi [1]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
        legend_right(ax)
    axes[-1][0].set_xlabel("cycles per stretch (frequency = cycles / stretch length)")
    fig.tight_layout()
    fig.savefig(out / "derivatives.png", dpi=DPI)
    plt.close(fig)
    return [out / "derivatives.png"]


def design_point(designs, design_id):
    """The landscape's (cycles_a, cycles_b) of the design itself and the axes' descriptions:
    a is the first stretch of the first experiment, b the first stretch of the last experiment
    (or, with one experiment, its second stretch), each at its first active input."""
    if designs is None:
        return None, "cycles a", "cycles b"
    sel = [k for k, x in enumerate(designs["design_id"]) if x == design_id]
    if not sel:
        return None, "cycles a", "cycles b"
    exps = list(dict.fromkeys(designs["experiment"][k] for k in sel))
    inputs = list(dict.fromkeys(designs["input"][k] for k in sel))

    def cycles(e, stretch):
        rows = [k for k in sel if designs["experiment"][k] == e and designs["stretch"][k] == stretch]
        rows.sort(key=lambda k: inputs.index(designs["input"][k]))
        return (int(designs["cycles"][rows[0]]), designs["input"][rows[0]]) if rows else (None, "?")

    if len(exps) > 1:
        (a, ia), (b, ib) = cycles(exps[0], 0), cycles(exps[-1], 0)
        la, lb = f"cycles of stretch 1 of {exps[0]} ({ia})", f"cycles of stretch 1 of {exps[-1]} ({ib})"
    else:
        (a, ia), (b, ib) = cycles(exps[0], 0), cycles(exps[0], 1)
        la, lb = f"cycles of stretch 1 of {exps[0]} ({ia})", f"cycles of stretch 2 of {exps[0]} ({ib})"
    return ((a, b) if a is not None and b is not None else None), la, lb


def plot_landscape(inp, out):
    path = inp / "landscape.parquet"
    if not path.exists():
        return []
    t, _ = read(path)
    designs = read(inp / "designs.parquet")[0] if (inp / "designs.parquet").exists() else None
    did = np.array(t["design_id"])
    a = np.array(t["cycles_a"])
    b = np.array(t["cycles_b"])
    phi = np.array(t["phi"], dtype=float)
    written = []
    for i in dict.fromkeys(did):
        sel = did == i
        xa, xb = np.unique(a[sel]), np.unique(b[sel])
        grid = np.full((len(xb), len(xa)), np.nan)
        ia = {v: k for k, v in enumerate(xa)}
        ib = {v: k for k, v in enumerate(xb)}
        for va, vb, p in zip(a[sel], b[sel], phi[sel]):
            grid[ib[vb], ia[va]] = p
        fig, ax = plt.subplots(figsize=(7.8, 5.4))
        im = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis",
                       extent=[xa[0] - 0.5, xa[-1] + 0.5, xb[0] - 0.5, xb[-1] + 0.5])
        fig.colorbar(im, ax=ax, label="criterion phi [1] (larger is better)")
        point, la, lb = design_point(designs, i)
        k = int(np.nanargmax(np.where(sel, phi, np.nan)))
        best = (a[k], b[k])
        if point is not None:
            p_phi = grid[ib[point[1]], ia[point[0]]] if point[0] in ia and point[1] in ib else np.nan
            ax.plot(*point, marker="*", ms=18, mfc="red", mec="white", mew=1.2, ls="none",
                    label=f"optimum (the design): {point[0]}, {point[1]} cycles, phi = {p_phi:.4g}")
        if point is None or tuple(point) != tuple(best):
            ax.plot(*best, marker="o", ms=11, mfc="none", mec="red", mew=1.8, ls="none",
                    label=f"largest phi on this slice: {best[0]}, {best[1]} cycles, phi = {phi[k]:.4g}")
        ax.set_xlabel(la)
        ax.set_ylabel(lb)
        ax.set_title(f"criterion landscape through the optimum: {i}\n(the other stretches held at the design)", fontsize=10)
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), fontsize=8, frameon=False)
        fig.tight_layout()
        written.append(out / f"landscape_{safe(i)}.png")
        fig.savefig(written[-1], dpi=DPI)
        plt.close(fig)
    return written


def main():
    ap = argparse.ArgumentParser(
        description="Plots of optimal injection designs (signals, amplitude limits, directional "
        "derivatives, criterion landscape) from the output folder of `freefall design optimize` "
        "or `freefall design validate`.",
        epilog="Figures go to DESIGN_DIR/plots/ unless --out DIR.",
    )
    ap.add_argument("input", type=Path, metavar="DESIGN_DIR",
                    help="output folder of `freefall design optimize --out DIR` or `design validate`")
    ap.add_argument("--out", type=Path, metavar="DIR", help="folder for the PNGs (default: DESIGN_DIR/plots)")
    a = ap.parse_args()
    if not (a.input / "designs.parquet").exists():
        ap.exit(1, f"error: {a.input}: no designs.parquet (run `freefall design optimize --out {a.input}` first)\n")
    out = a.out or a.input / "plots"
    out.mkdir(parents=True, exist_ok=True)
    written = plot_signals(a.input, out) + plot_limits(a.input, out) + plot_derivatives(a.input, out) + plot_landscape(a.input, out)
    for w in written:
        print(w)


if __name__ == "__main__":
    main()
