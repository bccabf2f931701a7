//! Deterministic responses ("templates", thesis eq. "templates"):
//! `o_s(t, p) = IFFT[T_{oi->o}(f, p) o_i(f)]`, with the inputs zero-padded by (at least) one data
//! length before the FFT and the result cut back to the data length (thesis footnote on
//! circular FFTs). The engine is prepared once per set of input series: FFT plans, the frequency
//! grid's parameter-independent model quantities and the injection spectra. Every evaluation
//! then costs one model evaluation per bin and one inverse FFT per output series.
//!
//! An optional per-bin left filter `W(f)` (an `N x N` matrix, e.g. a whitening filter's
//! frequency response) is applied before the inverse FFT, so filtered templates and filtered
//! derivatives come at no extra FFT cost.

use std::sync::Arc;

use num_complex::Complex64;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};

use crate::data::Series;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::numerics::fft::fast_len;

pub struct TemplateEngine<'m, M: ClosedLoopModel<N>, const N: usize> {
    model: &'m M,
    n: usize,
    m: usize,
    dt: f64,
    points: Vec<M::Point>,
    /// `inputs_f[e][c][k]`: spectrum of experiment e's input c (zero-padded), `None` if zero.
    inputs_f: Vec<Vec<Option<Vec<Complex64>>>>,
    fwd: Arc<dyn RealToComplex<f64>>,
    inv: Arc<dyn ComplexToReal<f64>>,
}

impl<'m, M: ClosedLoopModel<N>, const N: usize> TemplateEngine<'m, M, N> {
    /// `inputs[e][c]` is experiment e's guidance series on input c, all of length `n`.
    pub fn new(model: &'m M, inputs: &[Vec<Vec<f64>>], dt: f64) -> Self {
        let n = inputs
            .first()
            .and_then(|e| e.first())
            .map_or(0, |c| c.len());
        let m = fast_len(2 * n.max(1));
        let mut planner = RealFftPlanner::<f64>::new();
        let fwd = planner.plan_fft_forward(m);
        let inv = planner.plan_fft_inverse(m);
        let nbins = m / 2 + 1;
        let df = 1.0 / (m as f64 * dt);
        // The DC bin is evaluated just above zero: controllers with an integrator are singular
        // at s = 0, while the closed loop has a finite limit there.
        let points = (0..nbins)
            .map(|k| model.prepare(if k == 0 { 1e-6 * df } else { k as f64 * df }))
            .collect();
        let inputs_f = inputs
            .iter()
            .map(|exp| {
                (0..N)
                    .map(|c| {
                        let x = exp.get(c)?;
                        if x.iter().all(|v| *v == 0.0) {
                            return None;
                        }
                        let mut buf = vec![0.0; m];
                        buf[..n].copy_from_slice(x);
                        let mut spec = fwd.make_output_vec();
                        fwd.process(&mut buf, &mut spec).expect("FFT sizes match");
                        Some(spec)
                    })
                    .collect()
            })
            .collect();
        TemplateEngine {
            model,
            n,
            m,
            dt,
            points,
            inputs_f,
            fwd,
            inv,
        }
    }

    /// The same planned engine (FFT plans, input spectra, frequency points) for another model
    /// that shares this one's frequency points (e.g. a model extended by effects that act on the
    /// same base model): nothing is re-planned or re-transformed.
    pub fn for_model<'n, M2: ClosedLoopModel<N, Point = M::Point>>(
        &self,
        model: &'n M2,
    ) -> TemplateEngine<'n, M2, N> {
        TemplateEngine {
            model,
            n: self.n,
            m: self.m,
            dt: self.dt,
            points: self.points.clone(),
            inputs_f: self.inputs_f.clone(),
            fwd: self.fwd.clone(),
            inv: self.inv.clone(),
        }
    }

    /// The model the templates are computed for.
    pub fn model(&self) -> &'m M {
        self.model
    }

    pub fn len(&self) -> usize {
        self.n
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    pub fn dt(&self) -> f64 {
        self.dt
    }

    pub fn padded_len(&self) -> usize {
        self.m
    }

    pub fn n_experiments(&self) -> usize {
        self.inputs_f.len()
    }

    /// Frequencies of the padded grid's bins.
    pub fn frequencies(&self) -> Vec<f64> {
        let df = 1.0 / (self.m as f64 * self.dt);
        (0..self.points.len()).map(|k| k as f64 * df).collect()
    }

    /// Response spectrum `W T o_i` of experiment `e` at bin k into `acc` (per output channel).
    fn response(
        &self,
        e: usize,
        k: usize,
        t: &CMat<N>,
        filter: Option<&CMat<N>>,
    ) -> [Complex64; N] {
        let mut out = [Complex64::new(0.0, 0.0); N];
        for (c, inp) in self.inputs_f[e].iter().enumerate() {
            if let Some(x) = inp {
                for (i, o) in out.iter_mut().enumerate() {
                    *o += t[(i, c)] * x[k];
                }
            }
        }
        if let Some(w) = filter {
            let mut f = [Complex64::new(0.0, 0.0); N];
            for i in 0..N {
                for j in 0..N {
                    f[i] += w[(i, j)] * out[j];
                }
            }
            return f;
        }
        out
    }

    fn inverse(&self, mut spec: Vec<Complex64>, scratch: &mut [f64]) -> Vec<f64> {
        // realfft requires real DC and Nyquist bins for a real output.
        spec[0].im = 0.0;
        if self.m.is_multiple_of(2) {
            let last = spec.len() - 1;
            spec[last].im = 0.0;
        }
        self.inv
            .process(&mut spec, scratch)
            .expect("FFT sizes match");
        let norm = 1.0 / self.m as f64;
        scratch[..self.n].iter().map(|v| v * norm).collect()
    }

    /// Filter `N` series of length n by a per-bin matrix response on the padded grid
    /// (linear, not circular, convolution thanks to the padding), cut back to length n.
    pub fn filter_series(&self, x: &[Vec<f64>], filter: &[CMat<N>]) -> Vec<Vec<f64>> {
        let fwd = &self.fwd;
        let specs: Vec<Vec<Complex64>> = x
            .iter()
            .map(|c| {
                let mut buf = vec![0.0; self.m];
                buf[..c.len()].copy_from_slice(c);
                let mut spec = fwd.make_output_vec();
                fwd.process(&mut buf, &mut spec).expect("FFT sizes match");
                spec
            })
            .collect();
        let mut scratch = self.inv.make_output_vec();
        (0..N)
            .map(|o| {
                let spec: Vec<Complex64> = (0..specs[0].len())
                    .map(|k| (0..N).map(|i| filter[k][(o, i)] * specs[i][k]).sum())
                    .collect();
                self.inverse(spec, &mut scratch)
            })
            .collect()
    }

    /// Templates `out[e][i]` at parameters `p`, optionally filtered by `filter[k]` per bin.
    pub fn templates(&self, p: &[f64], filter: Option<&[CMat<N>]>) -> Series {
        let nb = self.points.len();
        let ne = self.n_experiments();
        let mut specs = vec![vec![vec![Complex64::new(0.0, 0.0); nb]; N]; ne];
        let mut tgrid = vec![CMat::<N>::zeros(); nb];
        self.model.transfer_grid(&self.points, p, &mut tgrid, None);
        for (k, t) in tgrid.iter().enumerate() {
            for (e, spec_e) in specs.iter_mut().enumerate() {
                let r = self.response(e, k, t, filter.map(|f| &f[k]));
                for i in 0..N {
                    spec_e[i][k] = r[i];
                }
            }
        }
        let mut scratch = self.inv.make_output_vec();
        specs
            .into_iter()
            .map(|exp| {
                exp.into_iter()
                    .map(|s| self.inverse(s, &mut scratch))
                    .collect()
            })
            .collect()
    }

    /// Templates at `p`, optionally filtered by `filter[k]` per bin, keeping only samples
    /// `from..n` of each series: `out[e][i]` has length `n - from`. The same numbers as
    /// [`Self::templates`] cut, without the full-length intermediates.
    pub fn templates_cut(&self, p: &[f64], filter: Option<&[CMat<N>]>, from: usize) -> Series {
        let mut out: Series = (0..self.n_experiments())
            .map(|_| Vec::with_capacity(N))
            .collect();
        self.templates_cut_with(p, filter, from, |e, _, t, norm| {
            out[e].push(t.iter().map(|v| v * norm).collect())
        });
        out
    }

    /// The templates of [`Self::templates_cut`] handed to `sink(e, i, t, norm)` one series at a
    /// time, unnormalised: the template is `norm * t`. The model is evaluated in blocks of
    /// bins that stay in cache, and the spectra and inverse-FFT buffers are per-thread scratch,
    /// so an evaluation allocates nothing of the series' size.
    pub fn templates_cut_with(
        &self,
        p: &[f64],
        filter: Option<&[CMat<N>]>,
        from: usize,
        mut sink: impl FnMut(usize, usize, &[f64], f64),
    ) {
        const BLOCK: usize = 128;
        let nb = self.points.len();
        let ne = self.n_experiments();
        let zero = Complex64::new(0.0, 0.0);
        let from = from.min(self.n);
        let norm = 1.0 / self.m as f64;
        // Per experiment, its non-zero inputs and their spectra.
        let active: Vec<Vec<(usize, &[Complex64])>> = self
            .inputs_f
            .iter()
            .map(|exp| {
                exp.iter()
                    .enumerate()
                    .filter_map(|(c, x)| x.as_deref().map(|x| (c, x)))
                    .collect()
            })
            .collect();
        let n_scratch = self.inv.get_scratch_len();
        crate::numerics::fft::with_buffers(ne * N * nb + n_scratch, self.m, |cbuf, out| {
            let (specs, scratch) = cbuf.split_at_mut(ne * N * nb);
            let mut tblock = [CMat::<N>::zeros(); BLOCK];
            for start in (0..nb).step_by(BLOCK) {
                let end = (start + BLOCK).min(nb);
                let tb = &mut tblock[..end - start];
                self.model
                    .transfer_grid(&self.points[start..end], p, tb, None);
                for (e, inputs) in active.iter().enumerate() {
                    if let (Some(f), &[(c, x)]) = (filter, inputs.as_slice()) {
                        // One injected input (the usual design): W T[:, c] x_c.
                        let out = &mut specs[e * N * nb..(e + 1) * N * nb];
                        let bins = tb.iter().zip(&x[start..end]).zip(&f[start..end]);
                        for (kk, ((t, xk), w)) in bins.enumerate() {
                            let u: [Complex64; N] = std::array::from_fn(|i| t[(i, c)] * xk);
                            for o in 0..N {
                                let mut acc = zero;
                                for (i, ui) in u.iter().enumerate() {
                                    acc += w[(o, i)] * ui;
                                }
                                out[o * nb + start + kk] = acc;
                            }
                        }
                        continue;
                    }
                    for (kk, t) in tb.iter().enumerate() {
                        let k = start + kk;
                        // u = T x (the order of `response`), then W u.
                        let mut u = [zero; N];
                        for &(c, x) in inputs {
                            for (i, ui) in u.iter_mut().enumerate() {
                                *ui += t[(i, c)] * x[k];
                            }
                        }
                        match filter {
                            Some(f) => {
                                let w = &f[k];
                                for o in 0..N {
                                    let mut acc = zero;
                                    for (i, ui) in u.iter().enumerate() {
                                        acc += w[(o, i)] * ui;
                                    }
                                    specs[(e * N + o) * nb + k] = acc;
                                }
                            }
                            None => {
                                for (o, uo) in u.into_iter().enumerate() {
                                    specs[(e * N + o) * nb + k] = uo;
                                }
                            }
                        }
                    }
                }
            }
            for e in 0..ne {
                for o in 0..N {
                    let spec = &mut specs[(e * N + o) * nb..(e * N + o + 1) * nb];
                    // realfft requires real DC and Nyquist bins for a real output.
                    spec[0].im = 0.0;
                    if self.m.is_multiple_of(2) {
                        spec[nb - 1].im = 0.0;
                    }
                    self.inv
                        .process_with_scratch(spec, out, scratch)
                        .expect("FFT sizes match");
                    sink(e, o, &out[from..self.n], norm);
                }
            }
        })
    }

    /// Templates and their parameter derivatives: `(o_s[e][i], d[k][e][i])`.
    pub fn templates_and_derivatives(
        &self,
        p: &[f64],
        filter: Option<&[CMat<N>]>,
    ) -> (Series, Vec<Series>) {
        let np = self.model.n_params();
        let nb = self.points.len();
        let ne = self.n_experiments();
        let zero = Complex64::new(0.0, 0.0);
        let mut specs = vec![vec![vec![zero; nb]; N]; ne];
        let mut dspecs = vec![vec![vec![vec![zero; nb]; N]; ne]; np];
        let mut tgrid = vec![CMat::<N>::zeros(); nb];
        let mut dgrid = vec![CMat::<N>::zeros(); nb * np];
        self.model
            .transfer_grid(&self.points, p, &mut tgrid, Some(&mut dgrid));
        for (k, t) in tgrid.iter().enumerate() {
            let d = &dgrid[k * np..(k + 1) * np];
            let w = filter.map(|f| &f[k]);
            for e in 0..ne {
                let r = self.response(e, k, t, w);
                for i in 0..N {
                    specs[e][i][k] = r[i];
                }
                for (q, dq) in d.iter().enumerate() {
                    let r = self.response(e, k, dq, w);
                    for i in 0..N {
                        dspecs[q][e][i][k] = r[i];
                    }
                }
            }
        }
        let mut scratch = self.inv.make_output_vec();
        let mut inv_all = |s: Series3| -> Series {
            s.into_iter()
                .map(|exp| {
                    exp.into_iter()
                        .map(|x| self.inverse(x, &mut scratch))
                        .collect()
                })
                .collect()
        };
        let t = inv_all(specs);
        let dt = dspecs.into_iter().map(&mut inv_all).collect();
        (t, dt)
    }
}

type Series3 = Vec<Vec<Vec<Complex64>>>;
