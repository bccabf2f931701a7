#!/usr/bin/env python3
"""Plot of a `freefall accel` output directory: accel.png, the amplitude spectral densities of the
total equivalent acceleration g12 (top) and g1 (bottom) of the whole run and of each --segment, with
their confidence bands, the model's projection Delta S_o Delta^H and (for the whole run) the noise
budget per source. Needs numpy, matplotlib and pyarrow."""
import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("out", type=Path, help="output directory of `freefall accel`")
    ap.add_argument("--png", type=Path, default=None, help="figure path (default OUT/accel.png)")
    args = ap.parse_args()
    psd = pq.read_table(args.out / "accel_psd.parquet").to_pydict()
    bud = pq.read_table(args.out / "budget.parquet").to_pydict()
    seg = np.array(psd["segment"])
    fig, axes = plt.subplots(2, 1, figsize=(8, 8), sharex=True)
    for ax, ch in zip(axes, ("g12", "g1")):
        for i, name in enumerate(dict.fromkeys(seg)):
            m = seg == name
            f = np.array(psd["f"])[m]
            s = np.array(psd[f"S_{ch}"])[m]
            color = f"C{i}"
            level = 100 * psd["level"][0]
            ax.loglog(f, np.sqrt(s), color=color, lw=1, label=f"estimate ({name})")
            ax.fill_between(f, np.sqrt(np.array(psd[f"S_{ch}_lo"])[m]), np.sqrt(np.array(psd[f"S_{ch}_hi"])[m]),
                            color=color, alpha=0.2, lw=0, label=f"{level:.0f}% band ({name})")
            if name == "all":
                ax.loglog(f, np.sqrt(np.array(psd[f"model_{ch}"])[m]), "k--", lw=1.2, label="model Delta S_o Delta^H")
        est = np.sqrt(np.array(psd[f"S_{ch}"]))
        # Budget terms far below the estimate (and the Nyquist zero of the derivative) would
        # stretch the axis over ten decades: show three decades below the lowest estimate.
        ax.set_ylim(est[est > 0].min() * 1e-3, est.max() * 3)
        src = np.array(bud["source"])
        for j, name in enumerate(dict.fromkeys(src)):
            m = src == name
            ax.loglog(np.array(bud["f"])[m], np.sqrt(np.array(bud[f"S_{ch}"])[m]), lw=0.7, ls=":",
                      color=f"C{(j + 3) % 10}", label=f"budget: {name}")
        ax.set_ylabel(f"sqrt(S_{ch}) [m s^-2 Hz^-1/2]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, ncol=2, loc="upper right")
    axes[-1].set_xlabel("f [Hz]")
    fig.suptitle("Total equivalent acceleration through Delta(p)")
    fig.tight_layout()
    fig.savefig(args.png or args.out / "accel.png", dpi=110)


if __name__ == "__main__":
    main()
