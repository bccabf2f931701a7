#!/usr/bin/env python3
"""Plot of a `freefall accel` output folder.

    python3 scripts/plot_accel.py ACCEL_DIR [--out DIR]

Figures go to ACCEL_DIR/plots/ unless --out DIR is given (the convention of every
scripts/plot_*.py). `freefall accel` runs this script (embedded in the binary; the environment
variable FREEFALL_PLOT_SCRIPT names another) as `python3 SCRIPT ACCEL_DIR`.

  accel.png  amplitude spectral densities of the total equivalent acceleration g12 (top) and g1
             (bottom) of the whole run and of each --segment, with their confidence bands, the
             model's projection Delta S_o Delta^H and (for the whole run) the noise budget per
             source (drawn on top: the dominant term lies on the estimate); the title names
             the parameters of Delta and of the noise model (metadata freefall.delta_parameters,
             freefall.noise_parameters); with compare.parquet (`freefall accel --compare REF`), the reference's
             whole-run g12 and its band in grey.
Units come from the tables (Parquet field metadata "unit", key-value "freefall.units"); a table
without them is read in the units freefall writes (f in Hz, S_* in m^2 s^-4 Hz^-1).
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
# Budget colours: none of the estimates' (C0-C2) nor grey or black (the reference, the model), so that
# a term lying on the estimate (the thruster's in g1) still shows.
BUDGET_COLORS = ["tab:red", "tab:purple", "tab:brown", "tab:pink", "gold", "tab:olive", "tab:cyan", "darkviolet"]
BUDGET_STYLES = [(0, (1, 1.5)), (0, (4, 1.5, 1, 1.5)), (0, (6, 2)), (0, (2, 2))]
# The units freefall writes, for tables written before they carried them.
DEFAULT_UNITS = {"f": "Hz", "S_g1": "m^2 s^-4 Hz^-1", "S_g12": "m^2 s^-4 Hz^-1"}


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
    """'m s^-2 Hz^-1/2' -> matplotlib mathtext superscripts."""
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


def asd_unit(psd_unit):
    """The unit of sqrt(S) for the PSD units freefall writes ('m^2 s^-4 Hz^-1')."""
    known = {"m^2 s^-4 Hz^-1": "m s^-2 Hz^-1/2", "m^2 Hz^-1": "m Hz^-1/2", "1": "1"}
    return known.get(psd_unit, f"({psd_unit})^1/2")


def parameters_line(meta):
    """Which parameters made the tables: key-value metadata "freefall.delta_parameters" and
    "freefall.noise_parameters" (written by `freefall accel`)."""
    def get(key):
        v = meta.get(key.encode())
        return v.decode() if v else "not recorded"
    return (f"p of $\\Delta$: {get('freefall.delta_parameters')}; "
            f"readout noise model: {get('freefall.noise_parameters')}")


def main():
    ap = argparse.ArgumentParser(
        description="Amplitude spectral densities of the total equivalent acceleration (accel.png) "
        "of a `freefall accel` output folder.",
        epilog="Figures go to ACCEL_DIR/plots/ unless --out DIR.",
    )
    ap.add_argument("input", type=Path, metavar="ACCEL_DIR", help="output folder of `freefall accel`")
    ap.add_argument("--out", type=Path, metavar="DIR", help="folder for accel.png (default: ACCEL_DIR/plots)")
    ap.add_argument("--png", type=Path, help=argparse.SUPPRESS)  # the old option: the figure's path
    args = ap.parse_args()
    if not (args.input / "accel_psd.parquet").exists():
        ap.exit(1, f"error: {args.input / 'accel_psd.parquet'}: not found (run `freefall accel ... --out {args.input}` first)\n")
    psd_t = pq.read_table(args.input / "accel_psd.parquet")
    units = dict(DEFAULT_UNITS)
    units.update(column_units(psd_t))
    psd = psd_t.to_pydict()
    bud = pq.read_table(args.input / "budget.parquet").to_pydict()
    seg = np.array(psd["segment"])
    f_all = np.array(psd["f"], dtype=float)
    level = 100 * psd["level"][0] if psd["level"] else 90
    fig, axes = plt.subplots(2, 1, figsize=(10, 8), sharex=True)
    for ax, ch in zip(axes, ("g12", "g1")):
        for i, name in enumerate(dict.fromkeys(seg)):
            m = seg == name
            f = f_all[m]
            color = f"C{i}"
            ax.loglog(f, np.sqrt(np.array(psd[f"S_{ch}"])[m]), color=color, lw=1.2, zorder=3,
                      label=f"estimate ({'whole run' if name == 'all' else name + ' s'})")
            ax.fill_between(f, np.sqrt(np.array(psd[f"S_{ch}_lo"])[m]), np.sqrt(np.array(psd[f"S_{ch}_hi"])[m]),
                            color=color, alpha=0.2, lw=0, zorder=2, label=f"{level:.0f} % band ({'whole run' if name == 'all' else name + ' s'})")
            if name == "all":
                ax.loglog(f, np.sqrt(np.array(psd[f"model_{ch}"])[m]), "k--", lw=1.3, zorder=4,
                          label="model $\\Delta S_o \\Delta^H$")
        cmp_path = args.input / "compare.parquet"
        if ch == "g12" and cmp_path.exists():
            c = pq.read_table(cmp_path).to_pydict()
            fc = np.array(c["f"], dtype=float)
            ax.loglog(fc, np.sqrt(np.array(c["S_g12_ref"], dtype=float)), color="0.3", lw=1.0, zorder=2.5,
                      label="reference (--compare), whole run")
            ax.fill_between(fc, np.sqrt(np.array(c["S_g12_ref_lo"], dtype=float)),
                            np.sqrt(np.array(c["S_g12_ref_hi"], dtype=float)), color="0.5", alpha=0.2, lw=0,
                            zorder=1.5, label="reference's band")
        est = np.sqrt(np.array(psd[f"S_{ch}"], dtype=float))
        # Budget terms far below the estimate (and the Nyquist zero of the derivative) would
        # stretch the axis over ten decades: show two decades below the estimate's 2nd percentile.
        ax.set_ylim(np.percentile(est[est > 0], 2) * 1e-2, est.max() * 3)
        src = np.array(bud["source"])
        for j, name in enumerate(dict.fromkeys(src)):
            m = src == name
            # On top of the estimate and the model: the dominant term (the thruster's in g1)
            # lies on them and would be hidden underneath.
            ax.loglog(np.array(bud["f"])[m], np.sqrt(np.array(bud[f"S_{ch}"])[m]), lw=1.8,
                      ls=BUDGET_STYLES[j % len(BUDGET_STYLES)], color=BUDGET_COLORS[j % len(BUDGET_COLORS)], zorder=5,
                      label=f"budget: {name}")
        unit = tex_unit(asd_unit(units.get(f"S_{ch}", DEFAULT_UNITS[f"S_{ch}"])))
        ax.set_ylabel(f"$\\sqrt{{S_{{{ch}}}}}$ [{unit}]")
        ax.set_title(f"{ch}", fontsize=10, loc="left")
        ax.grid(True, which="major", alpha=0.4)
        ax.grid(True, which="minor", alpha=0.12)
    axes[-1].set_xlabel(f"f [{units.get('f', 'Hz')}]")
    # One legend for both panels, right of them: it never covers a trace.
    h, lab = axes[0].get_legend_handles_labels()
    fig.legend(h, lab, loc="center left", bbox_to_anchor=(0.74, 0.5), fontsize=8, frameon=False)
    fig.suptitle("Total equivalent acceleration through $\\Delta(p)$: amplitude spectral densities\n"
                 + parameters_line(psd_t.schema.metadata or {}), fontsize=11)
    fig.tight_layout(rect=(0, 0, 0.74, 1))
    if args.png:
        png = args.png
        png.parent.mkdir(parents=True, exist_ok=True)
    else:
        png_dir = args.out or args.input / "plots"
        png_dir.mkdir(parents=True, exist_ok=True)
        png = png_dir / "accel.png"
    fig.savefig(png, dpi=DPI)
    print(png)


if __name__ == "__main__":
    main()
