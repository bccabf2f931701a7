#!/usr/bin/env python3
"""Redraw the thesis's Monte Carlo figures (sec. 4.5.5 and appendix "More on Monte Carlo
validation") from a `freefall campaign run` output directory.

    pip install -r scripts/requirements.txt
    python scripts/plot_campaign.py OUT_DIR [--png-dir DIR]

For every (scenario, design, estimator) group it writes four PNGs named
`<scenario>_<design>_<estimator>_<figure>.png`:
  parameters   per-parameter histograms of the converged estimates with the Gaussian PDF at the
               sample mean and sd (dashed: sample mean, solid: true value);
  variances    histograms of the fit variances sigma^2 with the Gaussian overlay;
  chi2         fit chi^2/nu next to the noise-only chi^2/nu, with N(1, sqrt(2/nu));
  correlation  Monte Carlo correlation matrix (lower triangle) and mean Fisher correlation (upper).
"""
import argparse
import math
import os
import sys

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402


def gaussian(ax, x, mean, sd, n, bins):
    """Overlay the Gaussian PDF scaled to the histogram counts."""
    if not (sd > 0 and np.isfinite(sd)):
        return
    width = bins[1] - bins[0]
    xs = np.linspace(bins[0], bins[-1], 200)
    ax.plot(xs, n * width * np.exp(-0.5 * ((xs - mean) / sd) ** 2) / (sd * math.sqrt(2 * math.pi)), "r-", lw=1.2)


def grid(k):
    cols = min(4, k)
    return math.ceil(k / cols), cols


def hist_panel(ax, values, title, truth=None):
    v = values[np.isfinite(values)]
    if v.size == 0:
        ax.set_title(title + " (no data)")
        return
    counts, bins, _ = ax.hist(v, bins=max(5, min(40, int(math.sqrt(v.size)) + 1)), color="0.75", edgecolor="0.4")
    mean, sd = float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else float("nan")
    gaussian(ax, v, mean, sd, v.size, bins)
    ax.axvline(mean, color="k", ls="--", lw=1)
    if np.isfinite(sd):
        ax.hlines(counts.max() / 2, mean - sd, mean + sd, color="k", lw=1)
    if truth is not None:
        ax.axvline(truth, color="b", ls="-", lw=1)
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=7)
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(4))
    ax.xaxis.get_offset_text().set_fontsize(7)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="campaign output directory")
    ap.add_argument("--png-dir", help="where to write the PNGs (default: OUT/plots)")
    a = ap.parse_args()
    png_dir = a.png_dir or os.path.join(a.out, "plots")
    os.makedirs(png_dir, exist_ok=True)
    real_path = os.path.join(a.out, "realizations.parquet")
    if not os.path.exists(real_path):
        sys.exit(f"error: {real_path}: not found (run `freefall campaign run ... --out {a.out}` first)")
    rows = pq.read_table(real_path).to_pydict()
    summary = pq.read_table(os.path.join(a.out, "summary.parquet")).to_pydict()
    corr = pq.read_table(os.path.join(a.out, "correlation.parquet")).to_pydict()
    params = list(dict.fromkeys(summary["parameter"]))
    truth = {}
    for s, d, e, p, t in zip(summary["scenario"], summary["design"], summary["estimator"], summary["parameter"], summary["truth"] if "truth" in summary else summary["true"]):
        truth[(s, d, e, p)] = t
    keys = np.array([f"{s}\x00{d}\x00{e}" for s, d, e in zip(rows["scenario"], rows["design"], rows["estimator"])])
    conv = np.array(rows["converged"], dtype=bool)
    written = []
    for key in dict.fromkeys(keys.tolist()):
        s, d, e = key.split("\x00")
        sel = (keys == key) & conv
        tag = f"{s}_{d}_{e}"
        r, c = grid(len(params))

        fig, axes = plt.subplots(r, c, figsize=(3.2 * c, 2.6 * r), squeeze=False)
        for ax, p in zip(axes.flat, params):
            hist_panel(ax, np.array(rows[p])[sel], p, truth[(s, d, e, p)])
        for ax in list(axes.flat)[len(params):]:
            ax.axis("off")
        fig.suptitle(f"{tag}: estimates ({int(sel.sum())} converged fits)", fontsize=10)
        fig.tight_layout()
        written.append(os.path.join(png_dir, f"{tag}_parameters.png"))
        fig.savefig(written[-1], dpi=110)
        plt.close(fig)

        fig, axes = plt.subplots(r, c, figsize=(3.2 * c, 2.6 * r), squeeze=False)
        for ax, p in zip(axes.flat, params):
            hist_panel(ax, np.array(rows[p + "_sigma"])[sel] ** 2, f"var({p})")
        for ax in list(axes.flat)[len(params):]:
            ax.axis("off")
        fig.suptitle(f"{tag}: fit variances", fontsize=10)
        fig.tight_layout()
        written.append(os.path.join(png_dir, f"{tag}_variances.png"))
        fig.savefig(written[-1], dpi=110)
        plt.close(fig)

        nu = np.array(rows["nu"])[sel]
        fig, axes = plt.subplots(1, 2, figsize=(8, 3.2), squeeze=False)
        for ax, col, title in zip(axes.flat, ["chi2_reduced", "noise_chi2_reduced"], ["(a) fit chi2/nu", "(b) noise chi2/nu"]):
            v = np.array(rows[col], dtype=float)[sel]
            hist_panel(ax, v, title)
            if nu.size and np.isfinite(v).any():
                sd = math.sqrt(2.0 / float(nu[0]))
                xs = np.linspace(1 - 4 * sd, 1 + 4 * sd, 200)
                ax.plot(xs, np.exp(-0.5 * ((xs - 1) / sd) ** 2) / (sd * math.sqrt(2 * math.pi)) * np.isfinite(v).sum() * (ax.patches[0].get_width() if ax.patches else 1), "g:", lw=1.2, label=f"N(1, sqrt(2/{int(nu[0])}))")
                ax.legend(fontsize=7)
        fig.suptitle(f"{tag}: fit vs noise chi^2", fontsize=10)
        fig.tight_layout()
        written.append(os.path.join(png_dir, f"{tag}_chi2.png"))
        fig.savefig(written[-1], dpi=110)
        plt.close(fig)

        m = np.eye(len(params))
        idx = {p: i for i, p in enumerate(params)}
        for cs, cd, ce, pi, pj, mc, fi in zip(corr["scenario"], corr["design"], corr["estimator"], corr["parameter_i"], corr["parameter_j"], corr["mc_correlation"], corr["fisher_correlation"]):
            if (cs, cd, ce) == (s, d, e):
                i, j = idx[pi], idx[pj]
                m[j, i] = mc
                m[i, j] = fi
        fig, ax = plt.subplots(figsize=(5.6, 4.8))
        im = ax.imshow(m, vmin=-1, vmax=1, cmap="RdBu_r")
        for i in range(len(params)):
            for j in range(len(params)):
                ax.text(j, i, f"{m[i, j]:.2f}", ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(params)), params, rotation=45, fontsize=8)
        ax.set_yticks(range(len(params)), params, fontsize=8)
        ax.set_title(f"{tag}\nlower: Monte Carlo, upper: mean Fisher", fontsize=9)
        fig.colorbar(im, ax=ax)
        fig.tight_layout()
        written.append(os.path.join(png_dir, f"{tag}_correlation.png"))
        fig.savefig(written[-1], dpi=110)
        plt.close(fig)
    for w in written:
        print(w)


if __name__ == "__main__":
    main()
