#!/usr/bin/env python3
"""Plots of a `freefall diagnose` output directory: psd.png (whitened residual spectra before and
after, against the whitened noise run, with the 90% band of white noise) and time_chi2.png
(chi^2/n per injection stretch). Needs numpy, matplotlib and pyarrow."""
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402


def main(out):
    out = Path(out)
    sp = pq.read_table(out / "spectra.parquet").to_pydict()
    keys = sorted({(e, c) for e, c, s in zip(sp["experiment"], sp["channel"], sp["stage"]) if s != "noise_run"})
    fig, axes = plt.subplots(len(keys), 1, figsize=(8, 2.6 * len(keys)), sharex=True, squeeze=False)
    for ax, (e, c) in zip(axes[:, 0], keys):
        for stage, color in (("noise_run", "0.6"), ("before", "tab:red"), ("after", "tab:blue")):
            exp = "noise" if stage == "noise_run" else e
            idx = [i for i in range(len(sp["f"])) if sp["stage"][i] == stage and sp["experiment"][i] == exp and sp["channel"][i] == c]
            if not idx:
                continue
            f = [sp["f"][i] for i in idx]
            ax.loglog(f, [sp["level"][i] for i in idx], color=color, label=stage.replace("_", " "))
            if stage == "after":
                ax.fill_between(f, [sp["lo90"][i] for i in idx], [sp["hi90"][i] for i in idx], color="tab:blue", alpha=0.15, label="90% white")
        ax.axhline(1.0, color="k", lw=0.5)
        ax.set_ylabel(f"{e} {c}\nwhitened PSD")
        ax.legend(fontsize=7, loc="upper left")
    axes[-1, 0].set_xlabel("f [Hz]")
    fig.tight_layout()
    fig.savefig(out / "psd.png", dpi=110)

    tc = pq.read_table(out / "time_chi2.parquet").to_pydict()
    keys = sorted(set(zip(tc["experiment"], tc["channel"])))
    fig, axes = plt.subplots(len(keys), 1, figsize=(8, 2.2 * len(keys)), sharex=True, squeeze=False)
    for ax, (e, c) in zip(axes[:, 0], keys):
        for stage, color in (("before", "tab:red"), ("after", "tab:blue")):
            idx = [i for i in range(len(tc["t_lo"])) if tc["stage"][i] == stage and tc["experiment"][i] == e and tc["channel"][i] == c]
            for i in idx:
                ax.plot([tc["t_lo"][i], tc["t_hi"][i]], [tc["excess"][i] + 1.0] * 2, color=color, lw=2, label=stage if i == idx[0] else None)
        ax.axhline(1.0, color="k", lw=0.5)
        ax.set_ylabel(f"{e} {c}\nchi2/n (rel. noise)")
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(out / "time_chi2.png", dpi=110)


if __name__ == "__main__":
    main(sys.argv[1])
