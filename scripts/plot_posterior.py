#!/usr/bin/env python3
"""Plots of a `freefall posterior` output folder.

    python3 scripts/plot_posterior.py POSTERIOR_DIR [--out DIR]

Figures go to POSTERIOR_DIR/plots/ unless --out DIR is given (the convention of every
scripts/plot_*.py). `freefall posterior` runs this script (embedded in the binary; the environment
variable FREEFALL_PLOT_SCRIPT names another) as `python3 SCRIPT POSTERIOR_DIR`.

  corner.png  every pair of sampled parameters, in units of the fit's Fisher sigma about the fit's
              estimate, (p - p_fit) / sigma_Fisher: the draws as 2-D histograms, the Fisher
              (Laplace) ellipses of 1 and 2 sigma (39 % and 86 % of a 2-D Gaussian) in red, and on
              the diagonal the marginal histograms with the Fisher Gaussian N(0, 1) in red. Where
              the posterior is Gaussian the draws fill the ellipses; where it is not (a bound, a
              curved valley) they do not.
  trace.png   every sampled parameter's chains against draw, in the same units.
Reads posterior.parquet (chain, draw, one column per parameter) and posterior.json (the sampled
parameters, the fit's estimates and covariance). Needs numpy, matplotlib and pyarrow.
"""
import argparse
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

DPI = 100
# chi^2 with 2 degrees of freedom at 1 and 2 sigma's 2-D probability: r^2 = 1 and 4.
LEVELS = (1.0, 2.0)


def standardised(folder):
    summary = json.loads((folder / "posterior.json").read_text())
    table = pq.read_table(folder / "posterior.parquet").to_pandas()
    names = summary["fisher_parameters"]
    by_name = {p["name"]: p for p in summary["parameters"]}
    cov = np.array(summary["fisher_covariance"], dtype=float)
    sig = np.sqrt(np.diag(cov))
    z = np.column_stack(
        [(table[n].to_numpy() - by_name[n]["fit_estimate"]) / s for n, s in zip(names, sig)]
    )
    corr = cov / np.outer(sig, sig)
    return summary, table, names, z, corr


def ellipse(c2, r):
    """Points of the ellipse x^T c2^-1 x = r^2 of the 2x2 correlation matrix c2."""
    w, v = np.linalg.eigh(c2)
    t = np.linspace(0, 2 * math.pi, 200)
    circle = np.vstack([np.cos(t), np.sin(t)]) * r
    return v @ (np.sqrt(np.maximum(w, 0))[:, None] * circle)


def corner(folder, out):
    summary, _, names, z, corr = standardised(folder)
    d = len(names)
    fig, axes = plt.subplots(d, d, figsize=(1.9 * d + 1, 1.9 * d + 1), squeeze=False)
    lim = max(4.0, float(np.nanpercentile(np.abs(z), 99.5)) * 1.1)
    grid = np.linspace(-lim, lim, 200)
    for i in range(d):
        for j in range(d):
            ax = axes[i][j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(z[:, i], bins=50, range=(-lim, lim), density=True, color="0.4")
                ax.plot(grid, np.exp(-grid**2 / 2) / math.sqrt(2 * math.pi), color="C3", lw=1)
                ax.set_yticks([])
            else:
                ax.hist2d(z[:, j], z[:, i], bins=40, range=[[-lim, lim], [-lim, lim]], cmap="Greys")
                c2 = corr[np.ix_([j, i], [j, i])]
                for r in LEVELS:
                    e = ellipse(c2, r)
                    ax.plot(e[0], e[1], color="C3", lw=1)
                ax.set_ylim(-lim, lim)
            ax.set_xlim(-lim, lim)
            if i == d - 1:
                ax.set_xlabel(names[j], fontsize=8)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(names[i], fontsize=8)
            elif j > 0:
                ax.set_yticklabels([])
            ax.tick_params(labelsize=7)
    ratios = ", ".join(
        f"{p['name']} {p['sd_over_fisher']:.2f}" for p in summary["parameters"] if not p["fixed"]
    )
    fig.suptitle(
        "posterior in units of the Fisher sigma about the fit; red: Fisher 1 and 2 sigma\n"
        f"sd / Fisher sigma: {ratios}",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(out / "corner.png", dpi=DPI)
    plt.close(fig)


def trace(folder, out):
    _, table, names, z, _ = standardised(folder)
    chains = table["chain"].to_numpy()
    draws = table["draw"].to_numpy()
    fig, axes = plt.subplots(len(names), 1, figsize=(9, 1.4 * len(names) + 0.8), sharex=True, squeeze=False)
    for k, name in enumerate(names):
        ax = axes[k][0]
        for c in np.unique(chains):
            sel = chains == c
            ax.plot(draws[sel], z[sel, k], lw=0.4, label=f"chain {c}")
        ax.set_ylabel(name, fontsize=8)
        ax.tick_params(labelsize=7)
    axes[-1][0].set_xlabel("draw")
    axes[0][0].set_title("(p - p_fit) / sigma_Fisher per chain", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "trace.png", dpi=DPI)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder", type=Path)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    out = a.out or a.folder / "plots"
    out.mkdir(parents=True, exist_ok=True)
    corner(a.folder, out)
    trace(a.folder, out)


if __name__ == "__main__":
    main()
