#!/usr/bin/env python3
"""Plots of optimal injection designs (thesis ch. 5).

Reads the output directory of `freefall design optimize --out DIR` or
`freefall design validate campaigns/optimal_design.toml` and writes PNGs beside it:

- signals_<design>.png: injections and readouts of each design (thesis fig. "synthetic data
  for optimal design"): one realization at the truth, per experiment;
- limits.png: largest allowed amplitude per constraint vs frequency for oi1 and oi12 (thesis
  figs. "maximum allowed amplitude"), the grid limit f_max marked;
- derivatives.png: normalised directional derivatives of the approximate design (the
  equivalence-theorem plot; the optimum's support sits at the maximum);
- landscape_<design>.png: the criterion with two stretches moved over the grid (a 2-D slice of
  the criterion landscape through the optimum).

Usage: python3 scripts/plot_design.py DIR
Dependencies: numpy, matplotlib, pyarrow.
"""
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402


def read(path):
    return pq.read_table(path).to_pydict()


def safe(name):
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def plot_signals(out):
    path = out / "signals.parquet"
    if not path.exists():
        return
    t = read(path)
    ids = list(dict.fromkeys(t["design_id"]))
    did = np.array(t["design_id"])
    exp = np.array(t["experiment"])
    cols = {k: np.array(t[k]) for k in ("t", "oi1", "oi12", "o1", "o12")}
    for d in ids:
        exps = list(dict.fromkeys(exp[did == d]))
        fig, axes = plt.subplots(2, len(exps), figsize=(6 * len(exps), 6), sharex=True, squeeze=False)
        for j, e in enumerate(exps):
            sel = (did == d) & (exp == e)
            th = cols["t"][sel] / 3600.0
            ax = axes[0][j]
            ax.plot(th, cols["oi1"][sel] * 1e6, lw=0.6, label="o_i1")
            ax.plot(th, cols["oi12"][sel] * 1e6, lw=0.6, label="o_i12")
            ax.set_title(f"{d}: {e} injections")
            ax.set_ylabel("guidance [um]")
            ax.legend(loc="upper right")
            ax = axes[1][j]
            ax.plot(th, cols["o1"][sel] * 1e6, lw=0.6, label="o1")
            ax.plot(th, cols["o12"][sel] * 1e6, lw=0.6, label="o12")
            ax.set_title(f"{e} readouts")
            ax.set_xlabel("time [h]")
            ax.set_ylabel("readout [um]")
            ax.legend(loc="upper right")
        fig.tight_layout()
        fig.savefig(out / f"signals_{safe(d)}.png", dpi=110)
        plt.close(fig)


def plot_limits(out):
    path = out / "limits.parquet"
    if not path.exists():
        return
    t = read(path)
    inp = np.array(t["input"])
    f = np.array(t["f_hz"])
    allowed = np.array(t["allowed"])
    names = [k for k in t if k.startswith("a_max_") and k != "a_max_m"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), squeeze=False)
    for j, i in enumerate(list(dict.fromkeys(inp))):
        ax = axes[0][j]
        sel = inp == i
        for n in names:
            ax.loglog(f[sel] * 1e3, np.array(t[n])[sel] * 1e6, label=n.replace("a_max_", "").replace("_", " "))
        ax.loglog(f[sel] * 1e3, np.array(t["a_max_m"])[sel] * 1e6, "k--", lw=2, label="combined (min)")
        fmax = f[sel & allowed].max()
        ax.axvline(fmax * 1e3, color="grey", ls=":", label="f_max")
        ax.set_title(f"largest allowed amplitude, {i}")
        ax.set_xlabel("f [mHz]")
        ax.set_ylabel("a_max [um]")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "limits.png", dpi=110)
    plt.close(fig)


def plot_derivatives(out):
    path = out / "derivatives.parquet"
    if not path.exists():
        return
    t = read(path)
    did = np.array(t["design_id"])
    exp = np.array(t["experiment"])
    c0 = np.array(t["cycles_oi1"])
    c1 = np.array(t["cycles_oi12"])
    d = np.array(t["normalized_derivative"])
    ids = list(dict.fromkeys(did))
    fig, axes = plt.subplots(len(ids), 1, figsize=(8, 2.6 * len(ids)), squeeze=False)
    for k, i in enumerate(ids):
        ax = axes[k][0]
        for e in dict.fromkeys(exp[did == i]):
            sel = (did == i) & (exp == e)
            if np.all(c0[sel] > 0) and np.all(c1[sel] > 0):
                # Simultaneous layout: the best pair per oi1 cycle count.
                xs = np.unique(c0[sel])
                ys = [d[sel][c0[sel] == x].max() for x in xs]
                ax.plot(xs, ys, ".-", label=f"{e} (max over oi12)")
            else:
                x = np.where(c0[sel] > 0, c0[sel], c1[sel])
                ax.plot(x, d[sel], ".-", label=e)
        ax.set_title(i)
        ax.set_xlabel("cycles per stretch")
        ax.set_ylabel("N_g tr(G M_i) / phi")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "derivatives.png", dpi=110)
    plt.close(fig)


def plot_landscape(out):
    path = out / "landscape.parquet"
    if not path.exists():
        return
    t = read(path)
    did = np.array(t["design_id"])
    a = np.array(t["cycles_a"])
    b = np.array(t["cycles_b"])
    phi = np.array(t["phi"])
    for i in dict.fromkeys(did):
        sel = did == i
        xa, xb = np.unique(a[sel]), np.unique(b[sel])
        grid = np.full((len(xb), len(xa)), np.nan)
        ia = {v: k for k, v in enumerate(xa)}
        ib = {v: k for k, v in enumerate(xb)}
        for va, vb, p in zip(a[sel], b[sel], phi[sel]):
            grid[ib[vb], ia[va]] = p
        fig, ax = plt.subplots(figsize=(6, 5))
        im = ax.imshow(grid, origin="lower", aspect="auto", extent=[xa[0] - 0.5, xa[-1] + 0.5, xb[0] - 0.5, xb[-1] + 0.5])
        fig.colorbar(im, ax=ax, label="phi")
        ax.set_xlabel("cycles of stretch 1 (first experiment)")
        ax.set_ylabel("cycles of stretch 1 (last experiment)")
        ax.set_title(f"criterion landscape: {i}")
        fig.tight_layout()
        fig.savefig(out / f"landscape_{safe(i)}.png", dpi=110)
        plt.close(fig)


def main():
    if len(sys.argv) != 2:
        sys.exit("usage: plot_design.py DIR (output of freefall design optimize/validate)")
    out = Path(sys.argv[1])
    if not (out / "designs.parquet").exists():
        sys.exit(f"{out}: no designs.parquet (run freefall design optimize --out {out})")
    plot_signals(out)
    plot_limits(out)
    plot_derivatives(out)
    plot_landscape(out)
    print(f"wrote plots to {out}")


if __name__ == "__main__":
    main()
