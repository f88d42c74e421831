"""Plot the SG fit against the true BTDF (de Rousiers 2012, Fig. 3) and print the fit errors.

Writes outputs/sg_fit/fig3.png (Beckmann, as the paper's Blinn-Phong lobes) and
fig3_ggx.png: in-plane slices of the transmitted lobe ``f_t |cos|`` (solid) and of the SG
read from the shipped table with ``sg_lookup`` (dashed) for incident angles 0, 30, 60, 80
and 88 degrees, two roughness values, entering (eta = 1.51) and leaving (1/1.51); each curve
pair is normalized by the true peak. Then prints, over a subsample of the table:

- relative L2 error over the sphere of SG vs true lobe, per region (lobe, NDF, entering or
  leaving, theta_o range, alpha range), for the moment-matched and the L2-optimal sharpness;
- energy error of the table against an independent Monte Carlo estimate (visible-normal
  sampling of microfacet.sample), at table nodes;
- interpolation error of the lookup at cell centres against a direct fit there.

Results are also saved as outputs/sg_fit/fit_errors.json.

    .venv/bin/python scripts/plot_sg_fit.py [--out outputs/sg_fit] [--quick] [--threads 1]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from torchrefract.optics import microfacet as mf, sg_fit, sg_table, sgfit

ROOT = Path(__file__).resolve().parent.parent
F64 = torch.float64
THETAS_DEG = (0, 30, 60, 80, 88)
THETA_BINS = ((0, 30), (30, 60), (60, 80), (80, 90.01))
ALPHA_BINS = ((1e-3, 0.01), (0.01, 0.1), (0.1, 0.4), (0.4, 1.0001))


def plot_fig3(table: sg_table.SGTable, dist: str, path: Path, alphas=(0.1, 0.3)) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, axes = plt.subplots(2, len(alphas), figsize=(6 * len(alphas), 8), squeeze=False)
    phi = torch.linspace(-90, 90, 1441, dtype=F64)  # signed angle from -n, degrees
    w = torch.stack([-torch.sin(torch.deg2rad(phi)), torch.zeros_like(phi),
                     -torch.cos(torch.deg2rad(phi))], -1)
    colors = plt.cm.viridis(np.linspace(0, 0.9, len(THETAS_DEG)))
    for row, (eta, label) in enumerate(((1.51, "entering, eta = 1.51"),
                                        (1 / 1.51, "leaving, eta = 1/1.51"))):
        for col, alpha in enumerate(alphas):
            ax = axes[row, col]
            for c, th in zip(colors, THETAS_DEG):
                t = math.radians(min(th, 89.99))
                wi = torch.tensor([math.sin(t), 0.0, math.cos(t)], dtype=F64)
                true = mf.eval(wi, w, alpha, eta, dist, radiance=False)
                amp, k, ang, e = sgfit.sg_lookup(table, torch.tensor(math.cos(t), dtype=F64),
                                                 torch.tensor(eta, dtype=F64),
                                                 torch.tensor(alpha, dtype=F64), dist)
                if float(e) < 1e-3 or float(true.max()) <= 0:
                    continue  # total internal reflection: no curve (as in the paper)
                p = torch.stack([-torch.sin(ang), torch.zeros_like(ang), -torch.cos(ang)])
                sg = sgfit.sg_eval(w, p, k, amp)
                peak = float(true.max())
                ax.plot(phi, true / peak, color=c, lw=1.8, label=f"{th} deg (E={float(e):.2f})")
                ax.plot(phi, sg / peak, color=c, lw=1.2, ls="--")
                if dist == "ggx":  # the L2-optimal sharpness (sg_lookup(..., sharpness="l2"))
                    amp2, k2, _, _ = sgfit.sg_lookup(
                        table, torch.tensor(math.cos(t), dtype=F64), torch.tensor(eta, dtype=F64),
                        torch.tensor(alpha, dtype=F64), dist, sharpness="l2")
                    ax.plot(phi, sgfit.sg_eval(w, p, k2, amp2) / peak, color=c, lw=1.0, ls=":")
            ax.set_title(f"{dist}, alpha = {alpha} (kappa = "
                         f"{mf.blinn_phong_from_alpha(alpha):.0f}), {label}", fontsize=10)
            ax.set_xlabel("outgoing direction in the plane of incidence (deg from -n)")
            ax.set_ylabel("lobe / true peak")
            ax.set_xlim(-90, 90)
            ax.legend(fontsize=8, title="incident angle", title_fontsize=8)
            ax.grid(alpha=0.3)
    extra = "; dotted: L2-optimal sharpness" if dist == "ggx" else ""
    fig.suptitle("True BTDF lobe f_t |cos| (solid) vs spherical Gaussian from the table "
                 f"(dashed: moment-matched sharpness{extra})")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


def _bin_stats(values: np.ndarray) -> str:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return "      -      "
    return f"{np.median(v):5.3f} ({np.quantile(v, 0.9):5.3f})"


def fit_errors(table: sg_table.SGTable, ti, ei, ai) -> dict:
    """Relative L2 errors at the chosen nodes, for both lobes, NDFs and sharpness modes."""
    out = {}
    for d, dist in enumerate(sg_table.DISTRIBUTIONS):
        for l_idx, lobe in enumerate(sg_table.LOBES):
            mom = np.full((len(ti), len(ei), len(ai)), np.nan)
            l2 = np.full_like(mom, np.nan)
            hemi = np.full_like(mom, np.nan)
            for j, a in enumerate(ai):
                fitted = table.data[d, l_idx][ti][:, ei][:, :, a].double()
                r = sg_fit.fit_error(table.theta[ti], table.eta[ei], float(table.alpha[a]), dist,
                                    lobe, fitted=fitted)
                mom[:, :, j] = r["rel_l2"].numpy()
                l2[:, :, j] = r["rel_l2_other"].numpy()
                hemi[:, :, j] = r["hemisphere"].numpy()
            out[(dist, lobe)] = {"moment": mom, "l2": l2, "hemisphere": hemi}
    return out


def print_fit_errors(table, ti, ei, ai, errs) -> dict:
    th = np.degrees(table.theta[ti])
    eta = table.eta[ei]
    al = table.alpha[ai]
    report = {}
    print("\nRelative L2 error of the SG vs the true lobe over the sphere: median (90th pct)")
    print("per theta_o range (rows) and alpha range (columns); moment-matched k | L2-optimal k")
    for (dist, lobe), e in errs.items():
        for side, sel_eta in (("entering", eta > 1.0001), ("leaving", eta < 0.9999)):
            print(f"\n  {lobe:8s} {dist:8s} {side} (eta in {eta[sel_eta].min():.2f}.."
                  f"{eta[sel_eta].max():.2f})")
            header = "".join(f"  alpha {lo:g}-{hi:g}".ljust(28) for lo, hi in ALPHA_BINS)
            print("    theta_o    " + header)
            for lo, hi in THETA_BINS:
                row = []
                for alo, ahi in ALPHA_BINS:
                    m = ((th >= lo) & (th < hi))[:, None, None] & sel_eta[None, :, None] \
                        & ((al >= alo) & (al < ahi))[None, None, :]
                    a, b = _bin_stats(e["moment"][m]), _bin_stats(e["l2"][m])
                    row.append(f"{a} | {b}")
                    report[f"{lobe}/{dist}/{side}/theta{lo}-{hi}/alpha{alo}-{ahi}"] = {
                        "moment_median": float(np.nanmedian(e["moment"][m]))
                        if np.isfinite(e["moment"][m]).any() else None,
                        "l2_median": float(np.nanmedian(e["l2"][m]))
                        if np.isfinite(e["l2"][m]).any() else None}
                print(f"    {lo:4.0f}-{min(hi, 90):3.0f}    " + "  ".join(row))
        h = e["hemisphere"]
        print(f"  {lobe} {dist}: SG mass on the wrong side of the surface: median "
              f"{np.nanmedian(1 - h):.4f}, 90th pct {np.nanquantile(1 - h, 0.9):.4f}, "
              f"max {np.nanmax(1 - h):.3f}")
    return report


def energy_errors(table, ti, ei, ai, n_samples: int = 2 ** 13) -> dict:
    """Table energy vs an independent MC estimate (visible-normal sampling), per NDF/lobe."""
    u = torch.quasirandom.SobolEngine(3, scramble=True, seed=17).draw(n_samples, dtype=F64)
    res = {}
    for d, dist in enumerate(sg_table.DISTRIBUTIONS):
        errs = {"transmit": [], "reflect": []}
        for a in ai:
            th = torch.tensor(table.theta[ti], dtype=F64).clamp(max=math.acos(sg_table.COS_GRAZING))
            wi = torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th)], -1)
            for e_idx in ei:
                wo, w, _ = mf.sample(wi[:, None, :], float(table.alpha[a]), float(table.eta[e_idx]),
                                     dist, u, sample_visible=True, radiance=False)
                e_t = (w * (wo[..., 2] < 0)).mean(-1)
                e_r = (w * (wo[..., 2] > 0)).mean(-1)
                errs["transmit"].append((table.data[d, 0, ti, e_idx, a, 0].double() - e_t).numpy())
                errs["reflect"].append((table.data[d, 1, ti, e_idx, a, 0].double() - e_r).numpy())
        for lobe, v in errs.items():
            v = np.abs(np.concatenate(v))
            res[f"{dist}/{lobe}"] = {"median": float(np.median(v)), "p99": float(np.quantile(v, 0.99)),
                                     "max": float(v.max())}
    print(f"\nEnergy: table vs independent Monte Carlo ({n_samples} visible-normal samples; "
          "its own noise is ~1e-3): absolute difference")
    for k, v in res.items():
        print(f"  {k:20s} median {v['median']:.1e}  99th pct {v['p99']:.1e}  max {v['max']:.1e}")
    return res


def interpolation_errors(table, ti, ei, ai) -> dict:
    """Lookup at cell centres vs a direct fit there (the error the table's resolution adds)."""
    th_c = 0.5 * (table.theta[ti] + table.theta[np.minimum(ti + 1, len(table.theta) - 1)])
    eta_c = np.sqrt(table.eta[ei] * table.eta[np.minimum(ei + 1, len(table.eta) - 1)])
    res = {}
    for d, dist in enumerate(sg_table.DISTRIBUTIONS):
        de, dang, dlk, dang_w = [], [], [], []
        for a in ai:
            a_c = math.sqrt(table.alpha[a] * table.alpha[min(a + 1, len(table.alpha) - 1)])
            fit = sg_fit.fit_entries(th_c, eta_c, a_c, dist)[0]  # transmit (T, E, 4)
            amp, k, ang, e = sgfit.sg_lookup(
                table, torch.cos(torch.tensor(th_c, dtype=F64))[:, None],
                torch.tensor(eta_c, dtype=F64)[None, :], torch.tensor(a_c, dtype=F64), dist)
            ok = (fit[..., 0] > 1e-2) & (e > 1e-2)
            de.append((e - fit[..., 0]).abs().flatten().numpy())
            dang.append((ang - fit[..., 2]).abs()[ok].numpy())
            dang_w.append(((ang - fit[..., 2]).abs() * torch.exp(0.5 * fit[..., 1]))[ok].numpy())
            dlk.append((torch.log(k) - fit[..., 1]).abs()[ok].numpy())
        cat = [np.concatenate(x) for x in (de, dang, dang_w, dlk)]
        res[dist] = {name: {"median": float(np.median(v)), "p90": float(np.quantile(v, 0.9)),
                            "p99": float(np.quantile(v, 0.99))}
                     for name, v in zip(("energy_abs", "axis_rad", "axis_in_lobe_widths",
                                         "log_k"), cat)}
    print("\nInterpolation (transmit lobe, cell centres in theta_o, eta and alpha; energy > 1%):"
          " median / 90th / 99th percentile")
    for dist, r in res.items():
        for name, v in r.items():
            print(f"  {dist:8s} {name:20s} {v['median']:.2e} / {v['p90']:.2e} / {v['p99']:.2e}")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "outputs" / "sg_fit")
    ap.add_argument("--quick", action="store_true", help="fewer table entries")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    table = sgfit.load_sg_table()
    print(f"table {sg_table.SHIPPED_TABLE.name}: data {tuple(table.data.shape)}, key "
          f"{table.spec.key()}, build time {table.build_seconds:.0f} s")
    plot_fig3(table, "beckmann", args.out / "fig3.png")
    plot_fig3(table, "ggx", args.out / "fig3_ggx.png")
    step = 6 if args.quick else 3
    ti = np.arange(0, table.spec.n_theta, step)
    ti = np.unique(np.append(ti, table.spec.n_theta - 2))
    ei = np.array([0, 4, 8, 12, 20, 22, 24, 28, 32])  # excludes eta = 1 (a Dirac lobe)
    ai = np.arange(0, table.spec.n_alpha, step)
    ai = np.unique(np.append(ai, table.spec.n_alpha - 1))
    errs = fit_errors(table, ti, ei, ai)
    report = {"fit_rel_l2": print_fit_errors(table, ti, ei, ai, errs)}
    report["energy_vs_mc"] = energy_errors(table, ti, ei, ai)
    report["interpolation"] = interpolation_errors(table, ti[:-1], ei[:-1], ai[:-1])
    report["threads"] = torch.get_num_threads()
    report["seconds"] = time.perf_counter() - t0
    (args.out / "fit_errors.json").write_text(json.dumps(report, indent=1))
    print(f"\nwrote {args.out / 'fit_errors.json'} ({report['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
