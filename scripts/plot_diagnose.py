#!/usr/bin/env python3
"""Plots of a `freefall diagnose` output folder.

    python3 scripts/plot_diagnose.py DIAGNOSE_DIR [--out DIR]

Figures go to DIAGNOSE_DIR/plots/ unless --out DIR is given (the convention of every
scripts/plot_*.py). `freefall diagnose` runs this script (embedded in the binary; the environment
variable FREEFALL_PLOT_SCRIPT names another) as `python3 SCRIPT DIAGNOSE_DIR`.

  psd.png        whitened residual spectra of each experiment and channel before (wide, light) and
                 after (thin, dark, on top) the added effects, the whitened noise run (grey) and the 90 %
                 band of white noise;
  time_chi2.png  chi^2/n of each injection stretch over the noise run's level, before and after,
                 with the +-1 and +-2 sigma bands a chi^2 with the window's n samples gives
                 (white noise).
Both titles say what the diagnosis found ("nothing added" or "added: X, Y"), read from
report.json like report.md.
Units come from the tables (Parquet field metadata "unit", key-value "freefall.units").
Needs numpy, matplotlib and pyarrow.
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
# "before" wide and light underneath, "after" thin and dark on top: where they coincide (nothing
# added, or an effect that changes little) the dark line runs inside the light one and both show.
STYLE = {
    "noise_run": dict(color="0.55", lw=1.0, ls="-", alpha=0.9, zorder=2, label="noise run"),
    "before": dict(color="#f4a582", lw=4.0, ls="-", alpha=1.0, zorder=3, label="before (nominal model)"),
    "after": dict(color="#08306b", lw=1.0, ls="-", alpha=1.0, zorder=4, label="after"),
}


def verdict(out):
    """What the diagnosis found, from report.json (the source of report.md): "nothing added" or
    "added: X, Y" (the effects' names, in the order added)."""
    try:
        rep = json.loads((out / "report.json").read_text())
    except (OSError, ValueError):
        return None
    added = rep.get("effects_added") or []
    if not added:
        return "nothing added"
    return "added: " + ", ".join(str(a.get("name", "?")) for a in added)


def after_label(found):
    """The legend's name of "after": with nothing added it is the same fit as "before"."""
    if found == "nothing added":
        return "after (= before: nothing added)"
    return "after (with the added effects)" if found else "after"


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


def chi2_reduced_quantile(n, z):
    """Quantile of chi^2_n / n at the standard-normal z (Wilson-Hilferty; no scipy needed)."""
    h = 2.0 / (9.0 * n)
    return max(0.0, 1.0 - h + z * math.sqrt(h)) ** 3


def window_samples(out, tc):
    """Samples per window from report.json (field `n`), else from the span and the sample time."""
    n = {}
    try:
        rep = json.loads((out / "report.json").read_text())
        for stage in ("before", "after"):
            for ch in rep.get(stage, {}).get("per_experiment_channel", []):
                for w in ch.get("time", []):
                    n[(stage, ch["experiment"], ch["channel"], float(w["time_s"][0]))] = int(w["n"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    dt = None
    res = out / "residuals_after.parquet"
    if res.exists():
        t = np.array(pq.read_table(res, columns=["t"]).column("t").to_pylist()[:3], dtype=float)
        if t.size > 1:
            dt = float(t[1] - t[0])
    result = []
    for s, e, c, lo, hi in zip(tc["stage"], tc["experiment"], tc["channel"], tc["t_lo"], tc["t_hi"]):
        k = n.get((s, e, c, float(lo)))
        if k is None and dt:
            k = int(round((hi - lo) / dt))
        result.append(k)
    return result


def header(fig, title, handles, labels, ncol):
    """Title and legend above the panels, in a fixed height that does not depend on the figure's."""
    rows = math.ceil(len(handles) / ncol)
    extra = 0.19 * title.count("\n")  # inches per further title line
    top = 1.0 - (0.45 + extra + 0.22 * rows) / fig.get_figheight()
    fig.tight_layout(rect=(0, 0, 1, top))
    fig.suptitle(title, fontsize=10, y=1.0 - 0.08 / fig.get_figheight(), va="top")
    fig.legend(handles, labels, loc="upper center", ncol=ncol, fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 1.0 - (0.35 + extra) / fig.get_figheight()))


def plot_psd(out, png, found):
    table = pq.read_table(out / "spectra.parquet")
    u = column_units(table)
    sp = table.to_pydict()
    stage, exp, chan = (np.array(sp[k]) for k in ("stage", "experiment", "channel"))
    f, level = np.array(sp["f"], dtype=float), np.array(sp["level"], dtype=float)
    lo, hi = np.array(sp["lo90"], dtype=float), np.array(sp["hi90"], dtype=float)
    keys = sorted({(e, c) for e, c, s in zip(exp, chan, stage) if s != "noise_run"})
    fig, axes = plt.subplots(len(keys), 1, figsize=(8, 2.3 * len(keys) + 1.0), sharex=True, squeeze=False)
    for ax, (e, c) in zip(axes[:, 0], keys):
        band = (exp == e) & (chan == c) & (stage == "after")
        if band.any():
            ax.fill_between(f[band], lo[band], hi[band], color="tab:blue", alpha=0.12, lw=0, zorder=1,
                            label="90 % band of white noise")
        # The noise run first, "before" thick and translucent, "after" thin on top: both visible.
        for s in ("noise_run", "before", "after"):
            sel = (stage == s) & (exp == ("noise" if s == "noise_run" else e)) & (chan == c)
            if sel.any():
                st = dict(STYLE[s])
                if s == "after":
                    st["label"] = after_label(found)
                ax.loglog(f[sel], level[sel], **st)
        ax.axhline(1.0, color="k", lw=0.6, ls="--", zorder=1, label="white level (1)")
        ax.set_ylabel(f"{e} {c}\nwhitened PSD [{u.get('level', '1')}]", fontsize=8)
        ax.grid(True, which="major", alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[-1, 0].set_xlabel(f"f [{u.get('f', 'Hz')}]")
    h, lab = axes[0, 0].get_legend_handles_labels()
    title = "whitened residual PSD (1 = the whitened noise run's level)"
    header(fig, f"{title}\ndiagnosis: {found}" if found else title, h, lab, 3)
    fig.savefig(png, dpi=DPI)
    plt.close(fig)


def plot_time_chi2(out, png, found):
    table = pq.read_table(out / "time_chi2.parquet")
    u = column_units(table)
    tc = table.to_pydict()
    ns = window_samples(out, tc)
    keys = sorted(set(zip(tc["experiment"], tc["channel"])))
    fig, axes = plt.subplots(len(keys), 1, figsize=(8, 2.1 * len(keys) + 1.0), sharex=True, squeeze=False)
    for ax, (e, c) in zip(axes[:, 0], keys):
        rows = [i for i in range(len(tc["t_lo"])) if tc["experiment"][i] == e and tc["channel"][i] == c]
        # Expected scatter of chi^2_n / n (white noise, n samples per window): +-1 and +-2 sigma.
        banded = set()
        for i in rows:
            span = (tc["t_lo"][i], tc["t_hi"][i])
            if ns[i] and span not in banded:
                banded.add(span)
                for z, alpha, label in ((2, 0.10, "expected $\\pm 2\\sigma$ ($\\chi^2_n/n$)"), (1, 0.18, "expected $\\pm 1\\sigma$ ($\\chi^2_n/n$)")):
                    ax.fill_between(span, [chi2_reduced_quantile(ns[i], -z)] * 2, [chi2_reduced_quantile(ns[i], z)] * 2,
                                    color="tab:green", alpha=alpha, lw=0, zorder=1, label=label if len(banded) == 1 else None)
        for s in ("before", "after"):
            first = True
            for i in rows:
                if tc["stage"][i] != s:
                    continue
                st = dict(STYLE[s])
                st["lw"] = 7 if s == "before" else 2
                st["label"] = (after_label(found) if s == "after" else st["label"]) if first else None
                ax.plot([tc["t_lo"][i], tc["t_hi"][i]], [tc["excess"][i] + 1.0] * 2, solid_capstyle="butt", **st)
                first = False
        ax.axhline(1.0, color="k", lw=0.6, ls="--", zorder=1, label="noise run level (1)")
        # A loud stretch (a missing effect's chi^2/n of 50) would flatten the others on a linear
        # axis: a log axis when the levels span more than a decade.
        levels = [tc["excess"][i] + 1.0 for i in rows if tc["excess"][i] + 1.0 > 0]
        if levels and max(levels) / min(levels) > 10:
            ax.set_yscale("log")
        ax.set_ylabel(f"{e} {c}\n$\\chi^2/n$ / noise [{u.get('excess', '1')}]", fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[-1, 0].set_xlabel(f"t [{u.get('t_lo', 's')}]")
    handles = {}
    for ax in axes[:, 0]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    title = "$\\chi^2/n$ per injection stretch over the noise run's level"
    header(fig, f"{title}\ndiagnosis: {found}" if found else title, list(handles.values()), list(handles.keys()), 3)
    fig.savefig(png, dpi=DPI)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(
        description="Residual spectra (psd.png) and time-resolved chi^2 (time_chi2.png) of a "
        "`freefall diagnose` output folder.",
        epilog="Figures go to DIAGNOSE_DIR/plots/ unless --out DIR.",
    )
    ap.add_argument("input", type=Path, metavar="DIAGNOSE_DIR", help="output folder of `freefall diagnose`")
    ap.add_argument("--out", type=Path, metavar="DIR", help="folder for the PNGs (default: DIAGNOSE_DIR/plots)")
    a = ap.parse_args()
    if not (a.input / "spectra.parquet").exists():
        ap.exit(1, f"error: {a.input / 'spectra.parquet'}: not found (run `freefall diagnose DATASET.toml --out {a.input}` first)\n")
    png_dir = a.out or a.input / "plots"
    png_dir.mkdir(parents=True, exist_ok=True)
    found = verdict(a.input)
    plot_psd(a.input, png_dir / "psd.png", found)
    plot_time_chi2(a.input, png_dir / "time_chi2.png", found)
    print(png_dir / "psd.png")
    print(png_dir / "time_chi2.png")


if __name__ == "__main__":
    main()
