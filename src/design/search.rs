//! Searches over exact designs and the approximate-design certificate.
//!
//! - **Direct search** (thesis sec. 5.2): a compass/pattern search over continuous frequencies
//!   (in cycles per stretch), each evaluation pulling every frequency to the nearest grid node.
//! - **Exchange** (Fedorov-type; Fedorov 1972, Cook & Nachtsheim 1980): slot by slot, replace a
//!   stretch by the candidate that improves the criterion most, until no exchange improves it.
//! - **Multiplicative algorithm** for the approximate design (Silvey, Titterington & Torsney
//!   1978; Yu 2010): counts `n_i >= 0` per candidate with the experiment's stretch count `N_g`
//!   fixed per group (marginally restricted design, Cook & Thibodeau 1980), updated
//!   `n_i <- N_g n_i d_i^delta / sum_{j in g} n_j d_j^delta` with `d_i = tr(G M_i)`, `G` the
//!   gradient of `phi`. The result is rounded to the available stretches by efficient
//!   apportionment (Pukelsheim & Rieder 1992; Pukelsheim 1993, ch. 12) and polished by exchange.
//!
//! # Certificate (equivalence theorem)
//! `phi` is concave and positively homogeneous (see [`crate::design::criteria`]), so for any
//! design `M` and any design `M*` of the same layout, `phi(M*) <= tr(G(M) M*)` (Euler plus
//! concavity) `<= U(M) = sum_g N_g max_{i in g} tr(G(M) M_i)` (Pukelsheim 1993, ch. 5-7: the
//! general equivalence theorem; the bound is his efficiency bound of sec. 5.15 generalised to
//! the per-experiment stretch counts). `U` bounds every exact design of the layout, so an exact
//! design `E` has efficiency `phi(E) / phi(E_opt) >= phi(E) / U`. The reported maximum
//! directional derivative is `U / phi(M)` at the approximate optimum: 1 at the optimum of the
//! relaxation (for D-optimality it is `max_x d(x) / s` of the Kiefer-Wolfowitz theorem).
//!
//! With a fixed known part `M0` of the information ([`CandidateSet::base`]; the xy design's
//! standard x experiments), `phi(M0 + M)` is concave in `M` but no longer homogeneous in it:
//! Euler and concavity at `M0 + M` give `phi(M0 + M*) <= tr(G M0) + tr(G M*)`, so the bound is
//! `U = tr(G M0) + sum_g N_g max_{i in g} tr(G M_i)` (the same argument applied at `M0 + M`;
//! `M0 = 0` gives the bound above).

use nalgebra::DMatrix;

use super::criteria::{Criterion, Evaluation, Kind, Target};
use super::space::{CandidateSet, ExactDesign};
use super::DesignError;
use crate::numerics::tol::STRICT_IMPROVEMENT;

/// Search settings.
#[derive(Debug, Clone)]
pub struct OptimizeConfig {
    pub criterion: Criterion,
    /// Iterations of the multiplicative algorithm.
    pub multiplicative_iterations: usize,
    /// Stop the multiplicative algorithm when `phi / U >= 1 - tol`.
    pub tol: f64,
    /// Sweeps of the exchange algorithm.
    pub max_sweeps: usize,
}

impl OptimizeConfig {
    pub fn new(criterion: Criterion) -> Self {
        OptimizeConfig {
            criterion,
            // The multiplicative algorithm converges linearly; 3000 steps reach the 1e-5
            // efficiency gap on the candidate sets here, which the exchange sweeps then polish.
            multiplicative_iterations: 3000,
            tol: 1e-5,
            max_sweeps: 50,
        }
    }
}

/// The outcome of one search method.
#[derive(Debug, Clone)]
pub struct MethodResult {
    pub method: &'static str,
    pub design: ExactDesign,
    pub phi: f64,
    pub evaluations: usize,
}

/// Equivalence-theorem certificate of an exact design.
#[derive(Debug, Clone, Copy)]
pub struct Certificate {
    /// `phi` of the approximate (continuous-weight) design found.
    pub approximate_phi: f64,
    /// Upper bound `U` on `phi` of any design of the layout.
    pub upper_bound: f64,
    /// `U / phi(approximate)`: the normalised maximum directional derivative (1 at the optimum).
    pub max_directional_derivative: f64,
    /// `phi(exact) / U`: lower bound on the exact design's efficiency.
    pub efficiency_lower_bound: f64,
    pub iterations: usize,
}

/// Result of [`optimize`].
#[derive(Debug, Clone)]
pub struct Optimized {
    pub criterion: Criterion,
    pub design: ExactDesign,
    pub phi: f64,
    pub certificate: Certificate,
    pub methods: Vec<MethodResult>,
    /// Approximate-design counts per group and candidate.
    pub approximate: Vec<Vec<f64>>,
    /// Normalised directional derivatives `N_g tr(G M_i) / phi` at the approximate design, per
    /// group and candidate (the equivalence-theorem plot; bounded by `U/phi` per group).
    pub derivatives: Vec<Vec<f64>>,
}

fn dmat(np: usize, v: &[f64]) -> DMatrix<f64> {
    DMatrix::from_row_slice(np, np, v)
}

/// `phi` of a flat information matrix (0 when singular).
pub fn phi_flat(np: usize, flat: &[f64], target: &Target, c: Criterion) -> f64 {
    Evaluation::new(&dmat(np, flat), target).map_or(0.0, |e| e.phi(c))
}

/// Fedorov-type exchange from `start`.
pub fn exchange<const K: usize>(
    set: &CandidateSet<K>,
    target: &Target,
    c: Criterion,
    start: &ExactDesign,
    max_sweeps: usize,
) -> MethodResult {
    let np = set.np;
    let mut d = start.clone();
    let mut m = set.information_flat(&d);
    let mut phi = phi_flat(np, &m, target, c);
    let mut evals = 1;
    let mut base = vec![0.0; np * np];
    let mut trial = vec![0.0; np * np];
    for _ in 0..max_sweeps {
        let mut improved = false;
        for (g, group) in set.groups.iter().enumerate() {
            for slot in 0..d.choice[g].len() {
                let cur = d.choice[g][slot];
                for ((b, mv), cv) in base.iter_mut().zip(&m).zip(&group.candidates[cur].info) {
                    *b = mv - cv;
                }
                let mut best = (phi, cur);
                for (j, cand) in group.candidates.iter().enumerate() {
                    if j == cur {
                        continue;
                    }
                    for ((t, b), cv) in trial.iter_mut().zip(&base).zip(&cand.info) {
                        *t = b + cv;
                    }
                    let v = phi_flat(np, &trial, target, c);
                    evals += 1;
                    if v > best.0 * (1.0 + STRICT_IMPROVEMENT) && v > 0.0 {
                        best = (v, j);
                    }
                }
                if best.1 != cur {
                    d.choice[g][slot] = best.1;
                    for ((mv, b), cv) in m.iter_mut().zip(&base).zip(&group.candidates[best.1].info)
                    {
                        *mv = b + cv;
                    }
                    phi = best.0;
                    improved = true;
                }
            }
        }
        if !improved {
            break;
        }
    }
    MethodResult {
        method: "exchange",
        design: d,
        phi,
        evaluations: evals,
    }
}

/// The thesis's direct search: compass search on continuous cycles per (group, slot, input),
/// snapped to the nearest grid node at every evaluation. `cycles[g][slot][input]` starts it.
pub fn direct_search<const K: usize>(
    set: &CandidateSet<K>,
    target: &Target,
    c: Criterion,
    start: &ExactDesign,
) -> MethodResult {
    let np = set.np;
    // Coordinates: the cycles of every active input of every slot.
    let mut coords: Vec<(usize, usize, usize)> = Vec::new();
    let mut x: Vec<f64> = Vec::new();
    let mut m_max = 1usize;
    for (g, group) in set.groups.iter().enumerate() {
        for (slot, &i) in start.choice[g].iter().enumerate() {
            for (inp, cy) in group.candidates[i].cycles.iter().enumerate() {
                if let Some(m) = cy {
                    coords.push((g, slot, inp));
                    x.push(*m as f64);
                }
            }
        }
        for cand in &group.candidates {
            m_max = m_max.max(cand.cycles.iter().flatten().copied().max().unwrap_or(1));
        }
    }
    let snap = |x: &[f64]| -> Option<ExactDesign> {
        let mut d = start.clone();
        for (g, group) in set.groups.iter().enumerate() {
            for slot in 0..d.choice[g].len() {
                let mut cy = group.candidates[d.choice[g][slot]].cycles;
                for (k, &(gg, ss, inp)) in coords.iter().enumerate() {
                    if gg == g && ss == slot {
                        cy[inp] = Some((x[k].round().max(1.0) as usize).min(m_max));
                    }
                }
                d.choice[g][slot] = group.candidates.iter().position(|cand| cand.cycles == cy)?;
            }
        }
        Some(d)
    };
    let value =
        |x: &[f64]| snap(x).map_or(0.0, |d| phi_flat(np, &set.information_flat(&d), target, c));
    let mut best = value(&x);
    let mut evals = 1;
    let mut step = (m_max as f64 / 4.0).max(1.0);
    // Iteration limit: every pass either improves (on a finite lattice of designs) or halves
    // the step; the cap only guards against a criterion that keeps creeping up by rounding.
    let max_evals = 1000 * (x.len() + 1) * (m_max + 1);
    while step >= 0.5 && evals < max_evals {
        let mut improved = false;
        for k in 0..x.len() {
            for dir in [1.0, -1.0] {
                let mut y = x.clone();
                // Continuous harmonic numbers that round into 1..=m_max.
                y[k] = (y[k] + dir * step).clamp(0.5, m_max as f64 + 0.49);
                let v = value(&y);
                evals += 1;
                if v > best * (1.0 + STRICT_IMPROVEMENT) {
                    best = v;
                    x = y;
                    improved = true;
                    break;
                }
            }
        }
        if !improved {
            step *= 0.5;
        }
    }
    let design = snap(&x).unwrap_or_else(|| start.clone());
    MethodResult {
        method: "direct_search",
        design,
        phi: best,
        evaluations: evals,
    }
}

/// Efficient apportionment of weights `w` (summing to 1) into `n` integer counts
/// (Pukelsheim & Rieder 1992).
pub fn efficient_rounding(w: &[f64], n: usize) -> Vec<usize> {
    let support: Vec<usize> = (0..w.len()).filter(|&i| w[i] > 0.0).collect();
    let l = support.len() as f64;
    let mut counts = vec![0usize; w.len()];
    for &i in &support {
        counts[i] = ((n as f64 - 0.5 * l) * w[i]).ceil().max(0.0) as usize;
    }
    loop {
        let total: usize = counts.iter().sum();
        if total == n {
            break;
        }
        if total < n {
            let j = support
                .iter()
                .copied()
                .min_by(|&a, &b| (counts[a] as f64 / w[a]).total_cmp(&(counts[b] as f64 / w[b])))
                .expect("non-empty support");
            counts[j] += 1;
        } else {
            let j = support
                .iter()
                .copied()
                .filter(|&a| counts[a] > 0)
                .max_by(|&a, &b| {
                    ((counts[a] - 1) as f64 / w[a]).total_cmp(&((counts[b] - 1) as f64 / w[b]))
                })
                .expect("positive counts");
            counts[j] -= 1;
        }
    }
    counts
}

struct Approximate {
    counts: Vec<Vec<f64>>,
    phi: f64,
    upper: f64,
    derivatives: Vec<Vec<f64>>,
    iterations: usize,
}

/// Directional quantities `d_i = tr(G M_i)` and the bound `U` at counts `n`.
fn derivatives<const K: usize>(
    set: &CandidateSet<K>,
    target: &Target,
    c: Criterion,
    counts: &[Vec<f64>],
) -> Option<(f64, Vec<Vec<f64>>, f64)> {
    let np = set.np;
    let mut m = set.base.clone().unwrap_or_else(|| vec![0.0; np * np]);
    for (g, cs) in set.groups.iter().zip(counts) {
        for (cand, &n) in g.candidates.iter().zip(cs) {
            if n > 0.0 {
                for (a, b) in m.iter_mut().zip(&cand.info) {
                    *a += n * b;
                }
            }
        }
    }
    let ev = Evaluation::new(&dmat(np, &m), target)?;
    let phi = ev.phi(c);
    let grad = ev.gradient(c, target);
    let d: Vec<Vec<f64>> = set
        .groups
        .iter()
        .map(|g| {
            g.candidates
                .iter()
                .map(|cand| {
                    cand.info
                        .iter()
                        .zip(&grad)
                        .map(|(a, b)| a * b)
                        .sum::<f64>()
                        .max(0.0)
                })
                .collect()
        })
        .collect();
    // With fixed information M0 (`set.base`): phi(M0 + M*) <= tr(G (M0 + M*)) (Euler plus
    // concavity at M0 + M) = tr(G M0) + tr(G M*).
    let fixed: f64 = set
        .base
        .as_ref()
        .map_or(0.0, |b| b.iter().zip(&grad).map(|(a, g)| a * g).sum());
    let upper = fixed
        + set
            .groups
            .iter()
            .zip(&d)
            .map(|(g, dg)| g.slots as f64 * dg.iter().copied().fold(0.0, f64::max))
            .sum::<f64>();
    Some((phi, d, upper))
}

/// E-optimality bound `min_alpha sum_g N_g max_{i in g} sum_k alpha_k (P v_k)^T M_i (P v_k)` over
/// the simplex (`lambda_min(I~(M*)) <= tr(W I~(M*)) <= tr(P W P^T M*)` for any `W = sum_k
/// alpha_k v_k v_k^T`, `tr W = 1`), minimised by exponentiated subgradient steps.
fn e_bound<const K: usize>(
    set: &CandidateSet<K>,
    target: &Target,
    counts: &[Vec<f64>],
) -> Option<f64> {
    let np = set.np;
    let mut m = set.base.clone().unwrap_or_else(|| vec![0.0; np * np]);
    for (g, cs) in set.groups.iter().zip(counts) {
        for (cand, &n) in g.candidates.iter().zip(cs) {
            if n > 0.0 {
                for (a, b) in m.iter_mut().zip(&cand.info) {
                    *a += n * b;
                }
            }
        }
    }
    let ev = Evaluation::new(&dmat(np, &m), target)?;
    let pv = ev.projected_eigenvectors(target);
    let s = pv.len();
    // d[g][i][k] = (P v_k)^T M_i (P v_k); d0[k] = (P v_k)^T M0 (P v_k) for the fixed part.
    let d = quad_forms(set, &pv);
    let d0: Vec<f64> = match &set.base {
        Some(b) => pv.iter().map(|u| quad_form(np, b, u)).collect(),
        None => vec![0.0; s],
    };
    let bound = |alpha: &[f64]| -> (f64, Vec<f64>) {
        let mut total: f64 = d0.iter().zip(alpha).map(|(a, b)| a * b).sum();
        let mut grad = d0.clone();
        for (g, dg) in set.groups.iter().zip(&d) {
            let (best, val) = dg
                .iter()
                .enumerate()
                .map(|(i, di)| (i, di.iter().zip(alpha).map(|(a, b)| a * b).sum::<f64>()))
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap_or((0, 0.0));
            total += g.slots as f64 * val;
            for (gk, dk) in grad.iter_mut().zip(&dg[best]) {
                *gk += g.slots as f64 * dk;
            }
        }
        (total, grad)
    };
    let mut alpha = vec![0.0; s];
    alpha[0] = 1.0;
    let (mut best, _) = bound(&alpha);
    let mut alpha: Vec<f64> = vec![1.0 / s as f64; s];
    for t in 0..2000 {
        let (u, grad) = bound(&alpha);
        best = best.min(u);
        let scale = grad
            .iter()
            .copied()
            .fold(0.0, f64::max)
            .max(f64::MIN_POSITIVE);
        let eta = 2.0 / ((t + 1) as f64).sqrt();
        let mut sum = 0.0;
        for (a, gk) in alpha.iter_mut().zip(&grad) {
            *a *= (-eta * gk / scale).exp();
            sum += *a;
        }
        for a in alpha.iter_mut() {
            *a /= sum;
        }
    }
    Some(best)
}

/// Exponent of the phi_p surrogate used to move the E-optimal approximate design.
const E_SMOOTH_P: f64 = -12.0;

/// Directional derivatives of `phi_p(I~) = (tr I~^p / s)^(1/p)` up to a positive factor:
/// `d_i = sum_k lambda_k^(p-1) (P v_k)^T M_i (P v_k)`, normalised to a maximum of 1.
fn e_smooth_derivatives<const K: usize>(
    set: &CandidateSet<K>,
    target: &Target,
    counts: &[Vec<f64>],
) -> Option<Vec<Vec<f64>>> {
    let np = set.np;
    let mut m = set.base.clone().unwrap_or_else(|| vec![0.0; np * np]);
    for (g, cs) in set.groups.iter().zip(counts) {
        for (cand, &n) in g.candidates.iter().zip(cs) {
            for (a, b) in m.iter_mut().zip(&cand.info) {
                *a += n * b;
            }
        }
    }
    let ev = Evaluation::new(&dmat(np, &m), target)?;
    let pv = ev.projected_eigenvectors(target);
    let mut lam: Vec<f64> = ev
        .info_scaled
        .clone()
        .symmetric_eigen()
        .eigenvalues
        .iter()
        .copied()
        .collect();
    lam.sort_by(|a, b| a.total_cmp(b));
    let l0 = lam[0];
    let w: Vec<f64> = lam
        .iter()
        .map(|l| (l / l0).powf(E_SMOOTH_P - 1.0))
        .collect();
    let q = quad_forms(set, &pv);
    let d: Vec<Vec<f64>> = q
        .iter()
        .map(|dg| {
            dg.iter()
                .map(|di| di.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>().max(0.0))
                .collect()
        })
        .collect();
    let max = d.iter().flatten().copied().fold(0.0, f64::max);
    (max > 0.0).then(|| {
        d.into_iter()
            .map(|dg| dg.into_iter().map(|x| x / max).collect())
            .collect()
    })
}

/// `u^T M u` of a row-major `np x np` matrix.
fn quad_form(np: usize, m: &[f64], u: &[f64]) -> f64 {
    let mut acc = 0.0;
    for i in 0..np {
        let row: f64 = (0..np).map(|j| m[i * np + j] * u[j]).sum();
        acc += u[i] * row;
    }
    acc
}

/// `q[g][i][k] = u_k^T M_i u_k`.
fn quad_forms<const K: usize>(set: &CandidateSet<K>, pv: &[Vec<f64>]) -> Vec<Vec<Vec<f64>>> {
    let np = set.np;
    set.groups
        .iter()
        .map(|g| {
            g.candidates
                .iter()
                .map(|cand| pv.iter().map(|u| quad_form(np, &cand.info, u)).collect())
                .collect()
        })
        .collect()
}

fn multiplicative<const K: usize>(
    set: &CandidateSet<K>,
    target: &Target,
    cfg: &OptimizeConfig,
) -> Result<Approximate, DesignError> {
    let c = cfg.criterion;
    let delta = match (c.kind, c.on) {
        (Kind::D, _) => 1.0,
        (Kind::E, _) => 1.0 / (1.0 - E_SMOOTH_P),
        _ => 0.5,
    };
    let mut counts: Vec<Vec<f64>> = set
        .groups
        .iter()
        .map(|g| vec![g.slots as f64 / g.candidates.len() as f64; g.candidates.len()])
        .collect();
    let mut best: Option<Approximate> = None;
    let mut min_upper = f64::INFINITY;
    let mut it = 0;
    while it < cfg.multiplicative_iterations {
        it += 1;
        let Some((phi, d, upper)) = derivatives(set, target, c, &counts) else {
            return Err(DesignError::Singular(
                "the uniform approximate design over the candidates".into(),
            ));
        };
        min_upper = min_upper.min(upper);
        if best.as_ref().is_none_or(|b| phi > b.phi) {
            best = Some(Approximate {
                counts: counts.clone(),
                phi,
                upper,
                derivatives: d.clone(),
                iterations: it,
            });
        }
        if phi / min_upper >= 1.0 - cfg.tol {
            break;
        }
        // E: lambda_min is non-smooth; step along Kiefer's phi_p (p = E_SMOOTH_P) instead,
        // which tends to E-optimality as p -> -inf.
        let d = if c.kind == Kind::E {
            e_smooth_derivatives(set, target, &counts).unwrap_or(d)
        } else {
            d
        };
        for ((g, cs), dg) in set.groups.iter().zip(counts.iter_mut()).zip(&d) {
            let mut total = 0.0;
            for (n, &di) in cs.iter_mut().zip(dg) {
                *n *= di.powf(delta);
                total += *n;
            }
            if total > 0.0 {
                for n in cs.iter_mut() {
                    *n *= g.slots as f64 / total;
                }
            }
        }
    }
    let mut b = best.expect("at least one iteration");
    b.upper = min_upper;
    b.iterations = it;
    Ok(b)
}

/// Round approximate counts to an exact design (efficient rounding per group over the points
/// holding at least 1% of the group's stretches).
fn round<const K: usize>(set: &CandidateSet<K>, counts: &[Vec<f64>]) -> ExactDesign {
    let choice = set
        .groups
        .iter()
        .zip(counts)
        .map(|(g, cs)| {
            let total: f64 = cs.iter().sum();
            let w: Vec<f64> = cs
                .iter()
                // Weights below 1 % are the multiplicative algorithm's not-yet-zero tail.
                .map(|n| if n / total >= 0.01 { n / total } else { 0.0 })
                .collect();
            let sw: f64 = w.iter().sum();
            let w: Vec<f64> = w.iter().map(|x| x / sw).collect();
            efficient_rounding(&w, g.slots)
                .iter()
                .enumerate()
                .flat_map(|(i, &k)| std::iter::repeat_n(i, k))
                .collect()
        })
        .collect();
    ExactDesign { choice }
}

/// Optimise `cfg.criterion` over the exact designs of `set`: direct search and exchange from
/// `start` (typically the standard design), multiplicative algorithm + rounding + exchange; the
/// best design carries the certificate.
pub fn optimize<const K: usize>(
    set: &CandidateSet<K>,
    target: &Target,
    cfg: &OptimizeConfig,
    start: &ExactDesign,
) -> Result<Optimized, DesignError> {
    let c = cfg.criterion;
    let mut methods = Vec::new();
    methods.push(direct_search(set, target, c, start));
    methods.push(exchange(set, target, c, start, cfg.max_sweeps));
    let approx = multiplicative(set, target, cfg)?;
    let rounded = round(set, &approx.counts);
    let mut r = exchange(set, target, c, &rounded, cfg.max_sweeps);
    r.method = "multiplicative_rounded_exchange";
    methods.push(r);
    let best = methods
        .iter()
        .max_by(|a, b| a.phi.total_cmp(&b.phi))
        .expect("three methods")
        .clone();
    // Polish the best with exchange (no-op when already exchange-optimal).
    let polished = exchange(set, target, c, &best.design, cfg.max_sweeps);
    let (mut design, phi) = if polished.phi > best.phi {
        (polished.design, polished.phi)
    } else {
        (best.design, best.phi)
    };
    if phi <= 0.0 {
        return Err(DesignError::Singular(format!(
            "no design found with a non-singular information for {}",
            c.name()
        )));
    }
    for ch in design.choice.iter_mut() {
        ch.sort_unstable();
    }
    // The bound can also be evaluated at the exact design itself; keep the tighter one.
    let counts_exact: Vec<Vec<f64>> = set
        .groups
        .iter()
        .zip(&design.choice)
        .map(|(g, ch)| {
            let mut v = vec![0.0; g.candidates.len()];
            for &i in ch {
                v[i] += 1.0;
            }
            v
        })
        .collect();
    let upper_exact = derivatives(set, target, c, &counts_exact).map_or(f64::INFINITY, |x| x.2);
    let mut upper = approx.upper.min(upper_exact);
    if c.kind == Kind::E {
        // lambda_min is not differentiable where eigenvalues coincide: tighten the bound over
        // the spectraplex (any W = sum_k alpha_k v_k v_k^T gives a valid bound).
        for counts in [&approx.counts, &counts_exact] {
            upper = upper.min(e_bound(set, target, counts).unwrap_or(f64::INFINITY));
        }
    }
    let derivs = set
        .groups
        .iter()
        .zip(&approx.derivatives)
        .map(|(g, dg)| dg.iter().map(|d| g.slots as f64 * d / approx.phi).collect())
        .collect();
    Ok(Optimized {
        criterion: c,
        design,
        phi,
        certificate: Certificate {
            approximate_phi: approx.phi,
            upper_bound: upper,
            max_directional_derivative: upper / approx.phi,
            efficiency_lower_bound: phi / upper,
            iterations: approx.iterations,
        },
        methods,
        approximate: approx.counts,
        derivatives: derivs,
    })
}
