//! Deterministic responses ("templates", thesis eq. "templates"):
//! `o_s(t, p) = IFFT[T_{oi->o}(f, p) o_i(f)]`, with the inputs zero-padded by (at least) one data
//! length before the FFT and the result cut back to the data length (thesis footnote on
//! circular FFTs). The engine is prepared once per set of input series: FFT plans, the frequency
//! grid's parameter-independent model quantities and the injection spectra. Every evaluation
//! then costs one model evaluation per bin and one inverse FFT per output series.
//!
//! Every experiment keeps its own length `n_e` and is transformed on its own padded grid of
//! `m_e = fast_len(2 (l_e + n_e))` points, `f_k = k / (m_e dt)`, where `l_e` is the experiment's
//! lead-in: input samples known before its first output sample (the earlier segments of a run
//! with gaps), so that its templates carry the loop's response to them instead of starting from
//! rest. The templates are the samples `l_e..l_e + n_e` of the response. Experiments of equal
//! padded length share one grid (plans and model points are prepared once per distinct `m_e`,
//! in order of first appearance), so a set of equal-length experiments costs what it always did.
//!
//! An optional per-bin left filter `W(f)` (an `N x N` matrix, e.g. a whitening filter's
//! frequency response) is applied before the inverse FFT, so filtered templates and filtered
//! derivatives come at no extra FFT cost. A filter is given per grid ([`GridFilter`]), on that
//! grid's bins.

use std::sync::Arc;

use num_complex::Complex64;
use realfft::{ComplexToReal, RealToComplex};

use crate::data::Series;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::numerics::fft::fast_len;
use crate::numerics::tol::DC_BIN_FRACTION;

/// A per-bin filter for every grid of an engine: `filter[g][k]` on grid `g`'s bin `k`.
pub type GridFilter<const N: usize> = [Vec<CMat<N>>];

/// One padded FFT grid: its length, plans and the model's prepared frequency points.
#[derive(Clone)]
struct Grid<P> {
    m: usize,
    points: Vec<P>,
    fwd: Arc<dyn RealToComplex<f64>>,
    inv: Arc<dyn ComplexToReal<f64>>,
}

impl<P> Grid<P> {
    fn nbins(&self) -> usize {
        self.points.len()
    }
}

pub struct TemplateEngine<'m, M: ClosedLoopModel<N>, const N: usize> {
    model: &'m M,
    /// Length `n_e` of every experiment.
    lens: Vec<usize>,
    /// Lead-in `l_e` of every experiment (input samples before its first output sample).
    leads: Vec<usize>,
    /// Grid of every experiment (index into `grids`).
    grid_of: Vec<usize>,
    grids: Vec<Grid<M::Point>>,
    dt: f64,
    /// `inputs_f[e][c][k]`: spectrum of experiment e's input c (zero-padded), `None` if zero.
    inputs_f: Vec<Vec<Option<Vec<Complex64>>>>,
}

impl<'m, M: ClosedLoopModel<N>, const N: usize> TemplateEngine<'m, M, N> {
    /// `inputs[e][c]` is experiment e's guidance series on input c; each experiment has its own
    /// length (all inputs of one experiment have the same).
    pub fn new(model: &'m M, inputs: &[Vec<Vec<f64>>], dt: f64) -> Self {
        let lens: Vec<usize> = inputs
            .iter()
            .map(|e| e.first().map_or(0, |c| c.len()))
            .collect();
        Self::with_lengths(model, inputs, &lens, dt)
    }

    /// The same for experiments of lengths `lens[e]` whose inputs may be absent (`inputs[e]`
    /// missing or empty: no injection) or longer than `lens[e]`: the first
    /// `inputs[e][c].len() - lens[e]` samples are then the experiment's lead-in (see the module
    /// docs).
    pub fn with_lengths(model: &'m M, inputs: &[Vec<Vec<f64>>], lens: &[usize], dt: f64) -> Self {
        let leads: Vec<usize> = lens
            .iter()
            .enumerate()
            .map(|(e, &n)| {
                let len = inputs.get(e).and_then(|x| x.first()).map_or(0, |c| c.len());
                len.saturating_sub(n)
            })
            .collect();
        Self::with_leads(model, inputs, lens, &leads, dt)
    }

    /// The same with every experiment's lead-in `leads[e]` given: inputs longer than
    /// `leads[e] + lens[e]` carry a lead-out, guidance after the last output sample, which
    /// the padded grid holds too (`m_e = fast_len(2 (l_e + n_e + t_e))`).
    pub fn with_leads(
        model: &'m M,
        inputs: &[Vec<Vec<f64>>],
        lens: &[usize],
        leads: &[usize],
        dt: f64,
    ) -> Self {
        let mut grids: Vec<Grid<M::Point>> = Vec::new();
        let mut grid_of = Vec::with_capacity(lens.len());
        let leads = leads.to_vec();
        let spans: Vec<usize> = lens
            .iter()
            .enumerate()
            .map(|(e, &n)| {
                let len = inputs.get(e).and_then(|x| x.first()).map_or(0, |c| c.len());
                len.max(leads[e] + n)
            })
            .collect();
        for &span in &spans {
            let m = fast_len(2 * span.max(1));
            let g = match grids.iter().position(|g| g.m == m) {
                Some(g) => g,
                None => {
                    let nbins = m / 2 + 1;
                    let df = 1.0 / (m as f64 * dt);
                    // The DC bin is evaluated just above zero: controllers with an integrator
                    // are singular at s = 0, while the closed loop has a finite limit there.
                    let points = (0..nbins)
                        .map(|k| {
                            model.prepare(if k == 0 {
                                DC_BIN_FRACTION * df
                            } else {
                                k as f64 * df
                            })
                        })
                        .collect();
                    grids.push(Grid {
                        m,
                        points,
                        fwd: crate::numerics::fft::real_forward(m),
                        inv: crate::numerics::fft::real_inverse(m),
                    });
                    grids.len() - 1
                }
            };
            grid_of.push(g);
        }
        let inputs_f = (0..lens.len())
            .map(|e| {
                let grid = &grids[grid_of[e]];
                (0..N)
                    .map(|c| {
                        let x = inputs.get(e)?.get(c)?;
                        if x.iter().all(|v| *v == 0.0) {
                            return None;
                        }
                        let mut buf = vec![0.0; grid.m];
                        let len = x.len().min(spans[e]);
                        buf[..len].copy_from_slice(&x[..len]);
                        let mut spec = grid.fwd.make_output_vec();
                        grid.fwd
                            .process(&mut buf, &mut spec)
                            .expect("FFT sizes match");
                        Some(spec)
                    })
                    .collect()
            })
            .collect();
        TemplateEngine {
            model,
            lens: lens.to_vec(),
            leads,
            grid_of,
            grids,
            dt,
            inputs_f,
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
            lens: self.lens.clone(),
            leads: self.leads.clone(),
            grid_of: self.grid_of.clone(),
            grids: self.grids.clone(),
            dt: self.dt,
            inputs_f: self.inputs_f.clone(),
        }
    }

    /// The model the templates are computed for.
    pub fn model(&self) -> &'m M {
        self.model
    }

    /// Length of the longest experiment.
    pub fn len(&self) -> usize {
        self.lens.iter().copied().max().unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Length of every experiment.
    pub fn lens(&self) -> &[usize] {
        &self.lens
    }

    /// Length of experiment `e`.
    pub fn len_of(&self, e: usize) -> usize {
        self.lens[e]
    }

    /// Lead-in of experiment `e` (input samples before its first output sample).
    pub fn lead_of(&self, e: usize) -> usize {
        self.leads[e]
    }

    pub fn dt(&self) -> f64 {
        self.dt
    }

    /// Padded length of the first experiment's grid (of every grid when all experiments have
    /// the same length).
    pub fn padded_len(&self) -> usize {
        self.grids.first().map_or(0, |g| g.m)
    }

    /// Padded length of experiment `e`'s grid.
    pub fn padded_len_of(&self, e: usize) -> usize {
        self.grids[self.grid_of[e]].m
    }

    /// Padded length of every grid, in grid order (what a [`GridFilter`] is indexed by).
    pub fn padded_lens(&self) -> Vec<usize> {
        self.grids.iter().map(|g| g.m).collect()
    }

    /// The grid of experiment `e` (index into [`Self::padded_lens`]).
    pub fn grid_of(&self, e: usize) -> usize {
        self.grid_of[e]
    }

    pub fn n_experiments(&self) -> usize {
        self.inputs_f.len()
    }

    /// Frequencies of the first experiment's padded grid.
    pub fn frequencies(&self) -> Vec<f64> {
        self.frequencies_of(0)
    }

    /// Frequencies of experiment `e`'s padded grid.
    pub fn frequencies_of(&self, e: usize) -> Vec<f64> {
        let g = &self.grids[self.grid_of[e]];
        let df = 1.0 / (g.m as f64 * self.dt);
        (0..g.nbins()).map(|k| k as f64 * df).collect()
    }

    /// Response spectrum `W T o_i` of experiment `e` at bin k of its grid (per output channel).
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

    /// Inverse transform of a spectrum on experiment `e`'s grid, samples `from..from + n_e`.
    fn inverse(
        &self,
        e: usize,
        mut spec: Vec<Complex64>,
        scratch: &mut [f64],
        from: usize,
    ) -> Vec<f64> {
        let g = &self.grids[self.grid_of[e]];
        // realfft requires real DC and Nyquist bins for a real output.
        spec[0].im = 0.0;
        if g.m.is_multiple_of(2) {
            let last = spec.len() - 1;
            spec[last].im = 0.0;
        }
        g.inv
            .process(&mut spec, &mut scratch[..g.m])
            .expect("FFT sizes match");
        let norm = 1.0 / g.m as f64;
        scratch[from..from + self.lens[e]]
            .iter()
            .map(|v| v * norm)
            .collect()
    }

    /// A real scratch buffer as long as the longest grid.
    fn real_scratch(&self) -> Vec<f64> {
        vec![0.0; self.grids.iter().map(|g| g.m).max().unwrap_or(0)]
    }

    /// Filter `N` series of experiment `e` (its length) by a per-bin matrix response on its
    /// padded grid (linear, not circular, convolution thanks to the padding), cut back to its
    /// length.
    pub fn filter_series(&self, e: usize, x: &[Vec<f64>], filter: &GridFilter<N>) -> Vec<Vec<f64>> {
        let g = &self.grids[self.grid_of[e]];
        let filter = &filter[self.grid_of[e]];
        let specs: Vec<Vec<Complex64>> = x
            .iter()
            .map(|c| {
                let mut buf = vec![0.0; g.m];
                buf[..c.len()].copy_from_slice(c);
                let mut spec = g.fwd.make_output_vec();
                g.fwd.process(&mut buf, &mut spec).expect("FFT sizes match");
                spec
            })
            .collect();
        let mut scratch = self.real_scratch();
        (0..N)
            .map(|o| {
                let spec: Vec<Complex64> = (0..specs[0].len())
                    .map(|k| (0..N).map(|i| filter[k][(o, i)] * specs[i][k]).sum())
                    .collect();
                self.inverse(e, spec, &mut scratch, 0)
            })
            .collect()
    }

    /// Experiments on grid `g`, in order.
    fn experiments_on(&self, g: usize) -> impl Iterator<Item = usize> + '_ {
        (0..self.n_experiments()).filter(move |&e| self.grid_of[e] == g)
    }

    /// Templates `out[e][i]` at parameters `p`, optionally filtered per grid and bin.
    pub fn templates(&self, p: &[f64], filter: Option<&GridFilter<N>>) -> Series {
        let ne = self.n_experiments();
        let zero = Complex64::new(0.0, 0.0);
        let mut specs: Series3 = (0..ne)
            .map(|e| vec![vec![zero; self.grids[self.grid_of[e]].nbins()]; N])
            .collect();
        for (gi, grid) in self.grids.iter().enumerate() {
            let mut tgrid = vec![CMat::<N>::zeros(); grid.nbins()];
            self.model.transfer_grid(&grid.points, p, &mut tgrid, None);
            let exps: Vec<usize> = self.experiments_on(gi).collect();
            for (k, t) in tgrid.iter().enumerate() {
                for &e in &exps {
                    let r = self.response(e, k, t, filter.map(|f| &f[gi][k]));
                    for i in 0..N {
                        specs[e][i][k] = r[i];
                    }
                }
            }
        }
        let mut scratch = self.real_scratch();
        specs
            .into_iter()
            .enumerate()
            .map(|(e, exp)| {
                exp.into_iter()
                    .map(|s| self.inverse(e, s, &mut scratch, self.leads[e]))
                    .collect()
            })
            .collect()
    }

    /// Templates at `p`, optionally filtered per grid and bin, keeping only samples `from..n_e`
    /// of each series: `out[e][i]` has length `n_e - from`. The same numbers as
    /// [`Self::templates`] cut, without the full-length intermediates.
    pub fn templates_cut(&self, p: &[f64], filter: Option<&GridFilter<N>>, from: usize) -> Series {
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
        filter: Option<&GridFilter<N>>,
        from: usize,
        mut sink: impl FnMut(usize, usize, &[f64], f64),
    ) {
        const BLOCK: usize = 128;
        let ne = self.n_experiments();
        let zero = Complex64::new(0.0, 0.0);
        // Offset of experiment e's spectra (N series of its grid's bins) in the buffer.
        let mut offsets = Vec::with_capacity(ne + 1);
        offsets.push(0usize);
        for e in 0..ne {
            offsets.push(offsets[e] + N * self.grids[self.grid_of[e]].nbins());
        }
        let total = offsets[ne];
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
        let n_scratch = self
            .grids
            .iter()
            .map(|g| g.inv.get_scratch_len())
            .max()
            .unwrap_or(0);
        let m_max = self.grids.iter().map(|g| g.m).max().unwrap_or(0);
        crate::numerics::fft::with_buffers(total + n_scratch, m_max, |cbuf, out| {
            let (specs, scratch) = cbuf.split_at_mut(total);
            let mut tblock = [CMat::<N>::zeros(); BLOCK];
            for (gi, grid) in self.grids.iter().enumerate() {
                let nb = grid.nbins();
                let gf = filter.map(|f| &f[gi][..]);
                for start in (0..nb).step_by(BLOCK) {
                    let end = (start + BLOCK).min(nb);
                    let tb = &mut tblock[..end - start];
                    self.model
                        .transfer_grid(&grid.points[start..end], p, tb, None);
                    for e in self.experiments_on(gi) {
                        let inputs = &active[e];
                        let spec_e = &mut specs[offsets[e]..offsets[e + 1]];
                        if let (Some(f), &[(c, x)]) = (gf, inputs.as_slice()) {
                            // One injected input (the usual design): W T[:, c] x_c.
                            let bins = tb.iter().zip(&x[start..end]).zip(&f[start..end]);
                            for (kk, ((t, xk), w)) in bins.enumerate() {
                                let u: [Complex64; N] = std::array::from_fn(|i| t[(i, c)] * xk);
                                for o in 0..N {
                                    let mut acc = zero;
                                    for (i, ui) in u.iter().enumerate() {
                                        acc += w[(o, i)] * ui;
                                    }
                                    spec_e[o * nb + start + kk] = acc;
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
                            match gf {
                                Some(f) => {
                                    let w = &f[k];
                                    for o in 0..N {
                                        let mut acc = zero;
                                        for (i, ui) in u.iter().enumerate() {
                                            acc += w[(o, i)] * ui;
                                        }
                                        spec_e[o * nb + k] = acc;
                                    }
                                }
                                None => {
                                    for (o, uo) in u.into_iter().enumerate() {
                                        spec_e[o * nb + k] = uo;
                                    }
                                }
                            }
                        }
                    }
                }
            }
            for (e, &g) in self.grid_of.iter().enumerate() {
                let grid = &self.grids[g];
                let (nb, m, n, lead) = (grid.nbins(), grid.m, self.lens[e], self.leads[e]);
                let norm = 1.0 / m as f64;
                let from = from.min(n);
                for o in 0..N {
                    let off = offsets[e] + o * nb;
                    let spec = &mut specs[off..off + nb];
                    // realfft requires real DC and Nyquist bins for a real output.
                    spec[0].im = 0.0;
                    if m.is_multiple_of(2) {
                        spec[nb - 1].im = 0.0;
                    }
                    let sc = &mut scratch[..grid.inv.get_scratch_len()];
                    grid.inv
                        .process_with_scratch(spec, &mut out[..m], sc)
                        .expect("FFT sizes match");
                    sink(e, o, &out[lead + from..lead + n], norm);
                }
            }
        })
    }

    /// Templates and their parameter derivatives: `(o_s[e][i], d[k][e][i])`.
    pub fn templates_and_derivatives(
        &self,
        p: &[f64],
        filter: Option<&GridFilter<N>>,
    ) -> (Series, Vec<Series>) {
        let np = self.model.n_params();
        let ne = self.n_experiments();
        let zero = Complex64::new(0.0, 0.0);
        let nb_of = |e: usize| self.grids[self.grid_of[e]].nbins();
        let mut specs: Series3 = (0..ne).map(|e| vec![vec![zero; nb_of(e)]; N]).collect();
        let mut dspecs: Vec<Series3> = (0..np)
            .map(|_| (0..ne).map(|e| vec![vec![zero; nb_of(e)]; N]).collect())
            .collect();
        for (gi, grid) in self.grids.iter().enumerate() {
            let nb = grid.nbins();
            let mut tgrid = vec![CMat::<N>::zeros(); nb];
            let mut dgrid = vec![CMat::<N>::zeros(); nb * np];
            self.model
                .transfer_grid(&grid.points, p, &mut tgrid, Some(&mut dgrid));
            let exps: Vec<usize> = self.experiments_on(gi).collect();
            for (k, t) in tgrid.iter().enumerate() {
                let d = &dgrid[k * np..(k + 1) * np];
                let w = filter.map(|f| &f[gi][k]);
                for &e in &exps {
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
        }
        let mut scratch = self.real_scratch();
        let mut inv_all = |s: Series3| -> Series {
            s.into_iter()
                .enumerate()
                .map(|(e, exp)| {
                    exp.into_iter()
                        .map(|x| self.inverse(e, x, &mut scratch, self.leads[e]))
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
