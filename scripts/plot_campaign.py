#!/usr/bin/env python3
"""Draw the thesis's Monte Carlo figures (sec. 4.5.5 and appendix "More on Monte Carlo
validation") from a `freefall campaign run` (or `campaign merge`) output folder.

    pip install -r scripts/requirements.txt
    python3 scripts/plot_campaign.py CAMPAIGN_DIR [--out DIR]

Figures go to CAMPAIGN_DIR/plots/ unless --out DIR is given (the convention of every
scripts/plot_*.py). For every (scenario, design, estimator) group it writes four PNGs named
`<scenario>_<design>_<estimator>_<figure>.png`:
  parameters   per-parameter histograms of estimate - truth (converged fits), in the parameter's
               unit times a stated power of ten, with the Gaussian of the Monte Carlo mean and sd
               and the Gaussian of the mean Fisher sigma centred at the truth; the title gives
               bias/sigma_F, the bias over the mean Fisher sigma (not the summary table's
               bias_in_sigma, which is the bias over its standard error sd / sqrt(n));
  variances    histograms of the fit variances sigma^2 relative to their mean, with the Monte
               Carlo variance of the estimates marked;
  chi2         fit chi^2/nu next to the noise-only chi^2/nu, with N(1, sqrt(2/nu));
  correlation  Monte Carlo correlation matrix (lower triangle) and mean Fisher correlation (upper).
Units come from the tables (Parquet field metadata "unit", key-value "freefall.units", the
summary's `unit` column).
"""
import argparse
import json
import math
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

DPI = 100


def column_units(table):
    """Units per column: key-value metadata "freefall.units" (JSON), then field metadata "unit"."""
    units = {}
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


def tex_unit(u):
    """'s^-2' -> 's$^{-2}$' for matplotlib; '1' or '' -> '' (dimensionless)."""
    if u in (None, "", "1"):
        return ""
    out, i = [], 0
    while i < len(u):
        if u[i] == "^":
            j = i + 1
            while j < len(u) and (u[j].isdigit() or u[j] in "-/."):
                j += 1
            out.append("$^{" + u[i + 1:j] + "}$")
            i = j
        else:
            out.append(u[i])
            i += 1
    return "".join(out)


def bracket(u, power=0):
    """Axis-label unit: '[10$^{-9}$ s$^{-2}$]', '[1]' for dimensionless."""
    tu = tex_unit(u)
    scale = f"10$^{{{power}}}$" if power else ""
    body = " ".join(x for x in (scale, tu) if x)
    return f"[{body or '1'}]"


def squared(u):
    """The unit of a variance: 's' -> 's^2', 's^-2' -> 's^-4', 'm s^-2' -> '(m s^-2)^2'."""
    if u in (None, "", "1"):
        return "1"
    base, _, exp = u.partition("^")
    if base.isalpha() and (not exp or exp.lstrip("-").isdigit()):
        return f"{base}^{2 * int(exp or 1)}"
    return f"({u})^2"


def decade(x):
    """Power of ten that brings x to between 1 and 10."""
    return int(math.floor(math.log10(abs(x)))) if x and np.isfinite(x) else 0


def plain_ticks(ax):
    """No offset or scientific tick labels: the axis label states any scale."""
    fmt = matplotlib.ticker.ScalarFormatter(useOffset=False)
    fmt.set_scientific(False)
    ax.xaxis.set_major_formatter(fmt)
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(5))
    ax.tick_params(labelsize=7)


def gauss(ax, bins, n, mean, sd, **kw):
    """The Gaussian PDF scaled to a histogram of n values in equal bins."""
    if not (sd > 0 and np.isfinite(sd) and np.isfinite(mean)):
        return
    width = bins[1] - bins[0]
    lo, hi = min(bins[0], mean - 4 * sd), max(bins[-1], mean + 4 * sd)
    xs = np.linspace(lo, hi, 300)
    ax.plot(xs, n * width * np.exp(-0.5 * ((xs - mean) / sd) ** 2) / (sd * math.sqrt(2 * math.pi)), **kw)


def nbins(n):
    return max(5, min(40, int(math.sqrt(n)) + 1))


def grid(k):
    cols = min(4, k)
    return math.ceil(k / cols), cols


def fmt_num(x):
    return f"{x:.3g}" if np.isfinite(x) else "n/a"


def estimate_panel(ax, v, truth, sigma, name, unit):
    """Histogram of estimate - truth with the Monte Carlo and Fisher Gaussians."""
    v = v[np.isfinite(v)]
    if v.size == 0:
        ax.set_title(f"{name} (no converged fits)", fontsize=8)
        return
    sd = float(v.std(ddof=1)) if v.size > 1 else float("nan")
    ref = sigma if np.isfinite(sigma) and sigma > 0 else sd
    power = decade(ref)
    scale = 10.0 ** -power
    d = (v - truth) * scale
    _, bins, _ = ax.hist(d, bins=nbins(v.size), color="0.8", edgecolor="0.45", label="estimates - truth")
    mean = float(d.mean())
    gauss(ax, bins, v.size, mean, sd * scale, color="tab:red", lw=1.3, label="Monte Carlo N(mean, sd)")
    gauss(ax, bins, v.size, 0.0, sigma * scale, color="tab:blue", lw=1.3, ls="--", label="Fisher N(truth, mean $\\sigma_F$)")
    ax.axvline(0.0, color="k", lw=1, label="truth")
    ax.axvline(mean, color="tab:red", lw=1, ls=":", label="Monte Carlo mean")
    tu = tex_unit(unit)
    # The bias over the mean Fisher sigma (the summary table's bias_in_sigma is another quantity:
    # the bias over its standard error sd / sqrt(n)).
    bias = (mean / scale) / sigma if sigma > 0 else float("nan")
    ax.set_title(
        f"{name}, truth {truth:.6g} {tu}\nMC sd {fmt_num(sd)}, $\\sigma_F$ {fmt_num(sigma)}{' ' + tu if tu else ''}, "
        f"sd/$\\sigma_F$ {sd / sigma:.2f}, bias/$\\sigma_F$ {bias:+.2f}",
        fontsize=7,
    )
    ax.set_xlabel(f"{name} - truth {bracket(unit, power)}", fontsize=8)
    ax.set_ylabel("fits", fontsize=8)
    plain_ticks(ax)


def variance_panel(ax, sig, sd_mc, n_mc, name, unit):
    """Histogram of sigma^2 / mean(sigma^2), the Monte Carlo variance of the estimates marked."""
    var = sig[np.isfinite(sig)] ** 2
    if var.size == 0 or not var.mean() > 0:
        ax.set_title(f"var({name}) (no data)", fontsize=8)
        return
    m = float(var.mean())
    r = var / m
    _, bins, _ = ax.hist(r, bins=nbins(r.size), color="0.8", edgecolor="0.45", label="fit variance / mean")
    if r.size > 1:
        gauss(ax, bins, r.size, float(r.mean()), float(r.std(ddof=1)), color="tab:red", lw=1.3, label="Gaussian (sample mean, sd)")
    ax.axvline(1.0, color="k", lw=1, label="mean fit variance")
    if np.isfinite(sd_mc):
        mc = sd_mc ** 2 / m
        # The sample variance of n Gaussian values scatters by sqrt(2/(n-1)) of itself.
        se = mc * math.sqrt(2.0 / max(n_mc - 1, 1))
        ax.axvline(mc, color="tab:green", lw=1.3, ls="--", label="Monte Carlo variance of the estimates")
        ax.axvspan(mc - se, mc + se, color="tab:green", alpha=0.15, lw=0, zorder=0,
                   label="Monte Carlo variance $\\pm$ its standard error $\\sqrt{2/(n-1)}$")
    ax.set_title(f"var({name}): mean {m:.3g} {tex_unit(squared(unit))}\nMC variance / mean = {sd_mc ** 2 / m:.3f}", fontsize=7)
    ax.set_xlabel(f"$\\sigma^2$({name}) / mean [1]", fontsize=8)
    ax.set_ylabel("fits", fontsize=8)
    plain_ticks(ax)


def chi2_panel(ax, v, nu, title):
    v = v[np.isfinite(v)]
    if v.size == 0:
        ax.set_title(title + " (no data)", fontsize=8)
        return
    _, bins, _ = ax.hist(v, bins=nbins(v.size), color="0.8", edgecolor="0.45", label=f"{v.size} fits")
    if v.size > 1:
        gauss(ax, bins, v.size, float(v.mean()), float(v.std(ddof=1)), color="tab:red", lw=1.3, label=f"sample: mean {v.mean():.4f}, sd {v.std(ddof=1):.4f}")
    if nu:
        sd = math.sqrt(2.0 / nu)
        gauss(ax, bins, v.size, 1.0, sd, color="tab:blue", lw=1.3, ls="--", label=f"expected N(1, sqrt(2/{nu})): sd {sd:.4f}")
    ax.axvline(1.0, color="k", lw=1, label="1 (correct model)")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("$\\chi^2/\\nu$ [1]", fontsize=8)
    ax.set_ylabel("fits", fontsize=8)
    plain_ticks(ax)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, frameon=False)


def shared_legend(fig, axes):
    """One legend for all panels, below them."""
    for ax in axes:
        h, lab = ax.get_legend_handles_labels()
        if h:
            fig.legend(h, lab, loc="lower center", ncol=min(5, len(h)), fontsize=8, frameon=False)
            return


def main():
    ap = argparse.ArgumentParser(
        description="Monte Carlo figures of a `freefall campaign run` output folder "
        "(parameter and variance histograms, chi^2/nu, correlation matrix).",
        epilog="Figures go to CAMPAIGN_DIR/plots/ unless --out DIR.",
    )
    ap.add_argument("input", metavar="CAMPAIGN_DIR", help="output folder of `freefall campaign run` or `campaign merge`")
    ap.add_argument("--out", metavar="DIR", help="folder for the PNGs (default: CAMPAIGN_DIR/plots)")
    ap.add_argument("--png-dir", dest="out", help=argparse.SUPPRESS)  # the old name of --out
    a = ap.parse_args()
    real_path = os.path.join(a.input, "realizations.parquet")
    if not os.path.exists(real_path):
        sys.exit(f"error: {real_path}: not found (run `freefall campaign run ... --out {a.input}` first)")
    png_dir = a.out or os.path.join(a.input, "plots")
    os.makedirs(png_dir, exist_ok=True)
    real_t = pq.read_table(real_path)
    units = column_units(real_t)
    rows = real_t.to_pydict()
    summary_t = pq.read_table(os.path.join(a.input, "summary.parquet"))
    summary = summary_t.to_pydict()
    corr = pq.read_table(os.path.join(a.input, "correlation.parquet")).to_pydict()
    params = list(dict.fromkeys(summary["parameter"]))
    truth_col = summary["truth"] if "truth" in summary else summary["true"]  # parts before the rename
    truth = {}
    for s, d, e, p, t in zip(summary["scenario"], summary["design"], summary["estimator"], summary["parameter"], truth_col):
        truth[(s, d, e, p)] = t
    if "unit" in summary:
        for p, u in zip(summary["parameter"], summary["unit"]):
            units.setdefault(p, u)
    keys = np.array([f"{s}\x00{d}\x00{e}" for s, d, e in zip(rows["scenario"], rows["design"], rows["estimator"])])
    conv = np.array(rows["converged"], dtype=bool)
    written = []

    def save(fig, name):
        written.append(os.path.join(png_dir, name))
        fig.savefig(written[-1], dpi=DPI)
        plt.close(fig)

    for key in dict.fromkeys(keys.tolist()):
        s, d, e = key.split("\x00")
        sel = (keys == key) & conv
        tag = f"{s}_{d}_{e}"
        r, c = grid(len(params))
        n_conv, n_all = int(sel.sum()), int((keys == key).sum())

        fig, axes = plt.subplots(r, c, figsize=(3.3 * c, 2.9 * r + 0.6), squeeze=False)
        for ax, p in zip(axes.flat, params):
            v = np.array(rows[p], dtype=float)[sel]
            sig = np.array(rows[p + "_sigma"], dtype=float)[sel]
            sig = sig[np.isfinite(sig)]
            estimate_panel(ax, v, truth[(s, d, e, p)], float(sig.mean()) if sig.size else float("nan"), p, units.get(p, ""))
        for ax in list(axes.flat)[len(params):]:
            ax.axis("off")
        fig.suptitle(f"{tag}: estimates - truth ({n_conv} of {n_all} fits converged)", fontsize=10)
        shared_legend(fig, axes.flat)
        fig.tight_layout(rect=(0, 0.05, 1, 1))
        save(fig, f"{tag}_parameters.png")

        fig, axes = plt.subplots(r, c, figsize=(3.3 * c, 2.9 * r + 0.6), squeeze=False)
        for ax, p in zip(axes.flat, params):
            v = np.array(rows[p], dtype=float)[sel]
            v = v[np.isfinite(v)]
            sd = float(v.std(ddof=1)) if v.size > 1 else float("nan")
            variance_panel(ax, np.array(rows[p + "_sigma"], dtype=float)[sel], sd, v.size, p, units.get(p, ""))
        for ax in list(axes.flat)[len(params):]:
            ax.axis("off")
        fig.suptitle(f"{tag}: fit variances (Fisher $\\sigma^2$ of each fit) against the Monte Carlo variance", fontsize=10)
        shared_legend(fig, axes.flat)
        fig.tight_layout(rect=(0, 0.05, 1, 1))
        save(fig, f"{tag}_variances.png")

        nu = np.array(rows["nu"])[sel]
        nu0 = int(nu[0]) if nu.size else 0
        fig, axes = plt.subplots(1, 2, figsize=(10, 4.4), squeeze=False)
        for ax, col, title in zip(axes.flat, ["chi2_reduced", "noise_chi2_reduced"], ["(a) fit $\\chi^2/\\nu$", "(b) noise-only $\\chi^2/\\nu$"]):
            chi2_panel(ax, np.array(rows[col], dtype=float)[sel], nu0, title)
        fig.suptitle(f"{tag}: fit vs noise-only $\\chi^2/\\nu$ ($\\nu$ = {nu0})", fontsize=10)
        fig.tight_layout()
        save(fig, f"{tag}_chi2.png")

        m = np.eye(len(params))
        idx = {p: i for i, p in enumerate(params)}
        for cs, cd, ce, pi, pj, mc, fi in zip(corr["scenario"], corr["design"], corr["estimator"], corr["parameter_i"], corr["parameter_j"], corr["mc_correlation"], corr["fisher_correlation"]):
            if (cs, cd, ce) == (s, d, e):
                i, j = idx[pi], idx[pj]
                m[max(i, j), min(i, j)] = mc
                m[min(i, j), max(i, j)] = fi
        fig, ax = plt.subplots(figsize=(5.8, 5.0))
        im = ax.imshow(m, vmin=-1, vmax=1, cmap="RdBu_r")
        for i in range(len(params)):
            for j in range(len(params)):
                ax.text(j, i, f"{m[i, j]:.2f}", ha="center", va="center", fontsize=7,
                        color="w" if abs(m[i, j]) > 0.6 else "k")
        ax.set_xticks(range(len(params)), params, rotation=45, fontsize=8)
        ax.set_yticks(range(len(params)), params, fontsize=8)
        ax.set_title(f"{tag}\nlower triangle: Monte Carlo, upper: mean Fisher ({n_conv} fits)", fontsize=9)
        fig.colorbar(im, ax=ax, label="correlation coefficient [1]")
        fig.tight_layout()
        save(fig, f"{tag}_correlation.png")
    for w in written:
        print(w)


if __name__ == "__main__":
    main()
