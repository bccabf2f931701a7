#!/usr/bin/env python3
"""NumPy/SciPy peer of one campaign realization, for a side-by-side timing with freefall.

Per realization: simulate both standard experiments of the LPF-x model (templates at the truth
plus colored noise drawn from the model cross-PSD), whiten in the frequency domain with the
Cholesky factor of the PSD, and Gauss-Newton fit the 7 parameters (w1_sq, w12_sq, s21, a_df,
a_sus, dt1, dt12) from the scenario's guess, with a finite-difference Jacobian. Closed loop and
noise follow the conventions in README.md and src/model/ ("Closed loop", "Spectra, transforms,
likelihood"), implemented independently of freefall; the model numbers are read from lpf_x.toml.

    pip install -r scripts/requirements.txt
    python scripts/peer_fit.py [--realizations 5] [--scenario monte_carlo] [--model src/model/lpf_x.toml]

Prints the wall time per realization (simulation + fit) and the pulls (estimate - truth) / sigma.
"""
import argparse
import os
import time
import tomllib

import numpy as np
import scipy.linalg as sla

HERE = os.path.dirname(os.path.abspath(__file__))
NAMES = ["w1_sq", "w12_sq", "s21", "a_df", "a_sus", "dt1", "dt12"]


def zpk(c, s):
    num = c["gain"] * np.prod([s - z for z in c["zeros"]], axis=0) if c["zeros"] else c["gain"] * np.ones_like(s)
    den = np.prod([s - p for p in c["poles"]], axis=0) if c["poles"] else np.ones_like(s)
    return num / den


class Model:
    def __init__(self, spec):
        k = spec["constants"]
        self.mt = k["m_tm"] / k["m_sc"]
        self.g = k["gamma_x"]
        self.ctrl = spec["controllers"]
        self.noise = spec["noise"]

    def ops(self, f, p):
        w1, w12, s21, adf, asus, dt1, dt12 = p
        s = 2j * np.pi * f
        mt, g = self.mt, self.g
        F = f.size
        D = np.zeros((F, 2, 2), complex)
        D[:, 0, 0] = s**2 + (1 + 2 * mt) * w1 + mt * w12
        D[:, 0, 1] = g + mt * (w1 + w12)
        D[:, 1, 0] = w12
        D[:, 1, 1] = s**2 + w1 + w12 - 2 * g
        Sinv = np.array([[1, 0], [-s21, 1]], complex)
        cdf, csus = zpk(self.ctrl["drag_free"], s), zpk(self.ctrl["suspension"], s)
        AC = np.zeros((F, 2, 2), complex)
        AC[:, 0, 0] = adf * cdf
        AC[:, 0, 1] = mt * asus * csus
        AC[:, 1, 1] = asus * csus
        delta = D @ Sinv + AC
        return D, Sinv, AC, delta, s

    def transfer(self, f, p):
        D, Sinv, AC, delta, s = self.ops(f, p)
        T = np.zeros((f.size, 2, 2), complex)
        T[:, 0, 0] = np.exp(-s * p[5])
        T[:, 1, 1] = np.exp(-s * p[6])
        return np.linalg.solve(delta, AC @ T)

    def psd(self, f, p):
        D, Sinv, AC, delta, s = self.ops(f, p)
        rows = {"f_sc": [-1.0, 0.0], "f_1": [1 + self.mt, -1.0], "f_2": [self.mt, 1.0]}
        F = f.size
        acc = np.zeros((F, 2, 2), complex)
        ro = np.zeros((F, 2, 2), complex)
        for src in self.noise.values():
            lvl, kn = src["level"], src.get("f_knee", 1.0)
            asd = {"flat": lvl + 0 * f, "red": lvl * (1 + kn / f), "inverse_f": lvl * kn / f,
                   "relaxed": lvl * np.sqrt(1 + (kn / f) ** 4)}[src["shape"]]
            if src["enters"] in rows:
                gvec = np.array(rows[src["enters"]])
                acc += asd[:, None, None] ** 2 * np.outer(gvec, gvec)[None]
            else:
                i = 0 if src["enters"] == "o_1" else 1
                ro[:, i, i] += asd**2
        S = np.linalg.inv(Sinv)
        DS = D @ np.broadcast_to(Sinv, D.shape)
        inner = acc + DS @ ro @ np.conj(np.swapaxes(DS, 1, 2))
        di = np.linalg.inv(delta)
        del S
        return di @ inner @ np.conj(np.swapaxes(di, 1, 2))


def design_inputs(spec, n, dt):
    inj = spec["injections"]["standard"]
    t = np.arange(n) * dt
    start = inj.get("start_s", inj["gap_s"])
    out = []
    for amps, ch in [(inj["oi1_amplitude"], 0), (inj["oi12_amplitude"], 1)]:
        x = np.zeros((2, n))
        for k, (cyc, a) in enumerate(zip(inj["cycles"], amps)):
            t0 = start + k * (inj["stretch_s"] + inj["gap_s"])
            m = (t >= t0) & (t < t0 + inj["stretch_s"])
            x[ch, m] = a * np.sin(2 * np.pi * cyc / inj["stretch_s"] * (t[m] - t0))
        out.append(x)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--realizations", type=int, default=5)
    ap.add_argument("--scenario", default="monte_carlo")
    ap.add_argument("--model", default=os.path.join(HERE, "..", "src", "model", "lpf_x.toml"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--fmin", type=float, default=5e-4, help="lowest frequency bin fitted [Hz]")
    a = ap.parse_args()
    with open(a.model, "rb") as fh:
        spec = tomllib.load(fh)
    model = Model(spec)
    sc = spec["scenarios"][a.scenario]
    truth = np.array([sc["true"][k] for k in NAMES])
    guess = np.array([sc["guess"][k] for k in NAMES])
    dt = 1.0 / spec["sampling"]["analyse_hz"]
    n = int(round(spec["injections"]["standard"].get("duration_s", 10800.0) / dt))
    inputs = design_inputs(spec, n, dt)
    rng = np.random.default_rng(a.seed)

    # Prepared once (like freefall's per-design preparation): FFTs of the zero-padded inputs,
    # the noise Cholesky factors on the generation grid and the whitening factors on the data grid.
    fpad = np.fft.rfftfreq(2 * n, dt)
    fpad[0] = fpad[1] * 1e-3
    ipad = [np.fft.rfft(x, 2 * n, axis=1) for x in inputs]
    m3 = 3 * n
    fg = np.fft.rfftfreq(m3, dt)[1:]
    Lg = np.linalg.cholesky(model.psd(fg, truth))
    # Bins below fmin are dropped: on a finite stretch the steep red noise leaks there (the
    # thesis's high-pass); the lowest injection is at 1/1200 s.
    fmin = a.fmin
    fd_all = np.fft.rfftfreq(n, dt)[1:]
    keep = fd_all >= fmin
    fd = fd_all[keep]
    Ld = np.linalg.cholesky(model.psd(fd, truth))
    # A Hann window against the leakage of the steep red noise on a finite stretch, normalised
    # so that whitened noise has unit variance per real degree of freedom.
    win = np.hanning(n)
    scale = np.sqrt(4.0 / (n * dt)) / np.sqrt(np.mean(win**2))

    def templates(p):
        T = model.transfer(fpad, p)
        return [np.fft.irfft(np.einsum("fij,jf->if", T, X), 2 * n, axis=1)[:, :n] for X in ipad]

    def noise():
        z = (rng.standard_normal((fg.size, 2)) + 1j * rng.standard_normal((fg.size, 2))) / np.sqrt(2)
        X = np.einsum("fij,fj->fi", Lg, z) * np.sqrt(m3 / (2 * dt))
        spec_full = np.vstack([np.zeros((1, 2)), X])
        if m3 % 2 == 0:
            spec_full[-1] = spec_full[-1].real * np.sqrt(2)
        x = np.fft.irfft(spec_full, m3, axis=0).T
        return x[:, n:2 * n]

    def whiten(series):
        out = []
        for s in series:
            R = np.fft.rfft(s * win, axis=1)[:, 1:][:, keep].T * dt
            w = np.linalg.solve(Ld, R[:, :, None])[:, :, 0] * scale
            out.append(np.concatenate([w.real.ravel(), w.imag.ravel()]))
        return np.concatenate(out)

    times, pulls = [], []
    for r in range(a.realizations):
        t0 = time.perf_counter()
        sig = templates(truth)
        data_w = whiten([s + noise() for s in sig])
        p = guess.copy()
        step = np.maximum(np.abs(p), 1.0) * 1e-6
        step[[0, 1]] = 1e-10
        step[2] = 1e-7
        res = data_w - whiten(templates(p))
        chi2 = res @ res
        for _ in range(30):
            J = np.empty((res.size, 7))
            for k in range(7):
                q = p.copy()
                q[k] += step[k]
                J[:, k] = (whiten(templates(q)) - (data_w - res)) / step[k]
            dp = sla.lstsq(J, res, lapack_driver="gelsy")[0]
            p_new = p + dp
            res_new = data_w - whiten(templates(p_new))
            chi2_new = res_new @ res_new
            done = abs(chi2 - chi2_new) < 1e-4 * chi2_new
            p, res, chi2 = p_new, res_new, chi2_new
            if done:
                break
        cov = np.linalg.inv(J.T @ J)
        sigma = np.sqrt(np.diag(cov))
        times.append(time.perf_counter() - t0)
        pulls.append((p - truth) / sigma)
        nu = res.size - 7
        print(f"realization {r}: {times[-1]:.3f} s, chi2/nu = {chi2 / nu:.4f}, pulls " + " ".join(f"{x:+.2f}" for x in pulls[-1]), flush=True)
    t = np.array(times)
    print(f"peer: {t.size} realizations, median {np.median(t):.3f} s per realization ({1 / np.median(t):.2f} realizations/s on one process)")


if __name__ == "__main__":
    main()
