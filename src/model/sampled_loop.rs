//! The sampled-data (digital) loop as a discrete-time state-space realization: the one
//! realization that the time-domain engine (`sim::time_domain`) advances and whose one-step
//! transition matrix gives the digital models' closed-loop poles (thesis sec. 3.3 for the
//! plant, sec. 4.4.5 for the digital loop; Franklin, Powell & Workman, "Digital control of
//! dynamic systems", ch. 4).
//!
//! Continuous plant, coordinates `q` (one per readout): `q'' + K q + Gd q' = f - A u` with the
//! stiffness `K`, a velocity term `Gd` (damping effects) and the actuation `A` of the bare
//! commands `u`; readouts `o = S q`. State `x = [q; q'; y]` with one first-order lag state
//! `y_j` per lagged actuator column (`tau_j y_j' = w_j - y_j`, `w = -u`), so
//! `x' = A_c x + B_f f + B_u w`.
//!
//! Discretised exactly under the holds (force noise held over `[t_k, t_(k+1))`, commands over
//! `[t_k + tau, t_(k+1) + tau)`):
//! `x_(k+1) = Phi x_k + Gamma f_k + Gamma_now w_k + Gamma_prev w_(k-1)` with `Phi = Phi(h)`,
//! `Gamma = Gamma(h)`, `Gamma_now = Gamma(h - tau)`, `Gamma_prev = Phi(h - tau) Gamma(tau)`
//! (`Gamma_now = Gamma(h)`, `Gamma_prev = 0` when `tau = 0`; [`held_input`]).
//!
//! Each law `j` is a discrete difference equation in state-space form, read off its direct
//! form II transposed ([`Df2t`]): `c_j+ = A_j c_j + B_j e_j`, `u_j = C_j c_j + d_j e_j`, with
//! the error `e_j = o_j` of the free loop (no guidance, no noise). With the state
//! `v = [x; c; w_prev]` (`w_prev` only with a computation delay) the free loop is
//! `v_(k+1) = M v_k`:
//!
//! ```text
//!         [ Phi - Gn D So   -Gn C    Gp ]
//!   M  =  [ B So             A_c     0  ]      So = [S, 0]  (o = So x),
//!         [ -D So           -C       0  ]      D = diag(d_j), A_c, B, C block-diagonal,
//! ```
//! `Gn = Gamma_now`, `Gp = Gamma_prev`. Its eigenvalues are the closed-loop poles in `z`, and
//! `s = ln(z) / h`. Unlike the determinant of the operator matrix expanded into one
//! polynomial, the eigenvalues are not moved by the expansion's cancellations, so the twin
//! loops' near-double slow poles stay where they are.

use nalgebra::{DMatrix, Schur};
use num_complex::Complex64;

use super::closed_loop::ClosedLoopModel;
use super::discrete::{held_input, Df2t};
use super::lpf_x::{A_DF, A_SUS, DT1, DT12, S21};
use super::poly::RootsError;
use super::zpk::Zpk;
use super::{LpfX, LpfXy};

/// Iterations allowed to the Schur decomposition of the transition matrix, per state (as for
/// the polynomial roots of the continuous model, see `model::poly`).
const SCHUR_ITERATIONS_PER_STATE: usize = 100;

/// What the digital loop needs of a model: its continuous plant `q'' + K q = G f - A u` as
/// real matrices (the same `K`, `S`, `A C` and `T` its frequency-domain operators are made
/// of), one control law per column of `A C`, acting on that column's readout error.
pub trait DigitalPlant<const N: usize>: ClosedLoopModel<N> {
    /// The stiffness `K` of `D = s^2 + K` at `p`, rows and columns in readout order.
    fn plant_stiffness(&self, p: &[f64]) -> [[f64; N]; N];
    /// The sensing matrix `S` (`o = S q`) at `p`.
    fn plant_sensing(&self, p: &[f64]) -> [[f64; N]; N];
    /// The actuation `A`: column `j` is the force per unit mass of a unit command of law `j`
    /// (`A C = A diag(law_j)`, gains and actuation cross-talk included).
    fn plant_actuation(&self, p: &[f64]) -> [[f64; N]; N];
    /// The continuous control law of column `j` (discretised by the loop).
    fn column_law(&self, j: usize) -> &Zpk;
    /// The delay of each guidance input `oi_j` [s] (`T = diag(exp(-s dt_j))`).
    fn guidance_delays(&self, p: &[f64]) -> [f64; N];
}

impl DigitalPlant<2> for LpfX {
    fn plant_stiffness(&self, p: &[f64]) -> [[f64; 2]; 2] {
        self.stiffness(p)
    }

    fn plant_sensing(&self, p: &[f64]) -> [[f64; 2]; 2] {
        [[1.0, 0.0], [p[S21], 1.0]]
    }

    fn plant_actuation(&self, p: &[f64]) -> [[f64; 2]; 2] {
        [[p[A_DF], self.mt * p[A_SUS]], [0.0, p[A_SUS]]]
    }

    fn column_law(&self, j: usize) -> &Zpk {
        [&self.c_df, &self.c_sus][j]
    }

    fn guidance_delays(&self, p: &[f64]) -> [f64; 2] {
        [p[DT1], p[DT12]]
    }
}

impl DigitalPlant<7> for LpfXy {
    fn plant_stiffness(&self, p: &[f64]) -> [[f64; 7]; 7] {
        let k = self.stiffness(p);
        std::array::from_fn(|i| std::array::from_fn(|j| k[(i, j)]))
    }

    fn plant_sensing(&self, p: &[f64]) -> [[f64; 7]; 7] {
        let s = self.sensing(p);
        std::array::from_fn(|i| std::array::from_fn(|j| s[(i, j)]))
    }

    fn plant_actuation(&self, p: &[f64]) -> [[f64; 7]; 7] {
        let cols: [[f64; 7]; 7] = std::array::from_fn(|j| self.actuation_column(p, j));
        std::array::from_fn(|i| std::array::from_fn(|j| cols[j][i]))
    }

    fn column_law(&self, j: usize) -> &Zpk {
        self.law_zpk(j)
    }

    /// The x guidance delays; the y and phi guidance is not delayed (`T` of the operators).
    fn guidance_delays(&self, p: &[f64]) -> [f64; 7] {
        let mut d = [0.0; 7];
        d[0] = p[DT1];
        d[1] = p[DT12];
        d
    }
}

/// The plant's physical matrices at one parameter set (module doc), effects included.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlantMatrices<const N: usize> {
    /// Stiffness `K` [s^-2].
    pub k: [[f64; N]; N],
    /// Velocity-proportional force per unit mass `Gd` [s^-1].
    pub damping: [[f64; N]; N],
    /// Sensing `S`.
    pub s: [[f64; N]; N],
    /// Actuation of the bare commands through each column's actuator (behind its lag).
    pub actuation: [[f64; N]; N],
    /// Actuation of the bare commands that bypasses the lags (actuation cross-talk).
    pub direct: [[f64; N]; N],
    /// Each column's first-order lag time constant [s]; 0: none.
    pub lag: [f64; N],
}

impl<const N: usize> PlantMatrices<N> {
    /// The reference plant of `model` at `p` (no effects).
    pub fn of<M: DigitalPlant<N>>(model: &M, p: &[f64]) -> Self {
        PlantMatrices {
            k: model.plant_stiffness(p),
            damping: [[0.0; N]; N],
            s: model.plant_sensing(p),
            actuation: model.plant_actuation(p),
            direct: [[0.0; N]; N],
            lag: [0.0; N],
        }
    }

    /// `(A_c, B_f, B_u, active)`: the continuous state-space plant on the `3N` states
    /// `[q; q'; y]` and the indices of the states that exist (`q`, `q'` and the lagged
    /// columns' `y`).
    fn continuous(&self) -> (DMatrix<f64>, DMatrix<f64>, DMatrix<f64>, Vec<usize>) {
        let (nx, nz) = (2 * N, 3 * N);
        let mut a = DMatrix::<f64>::zeros(nz, nz);
        for i in 0..N {
            a[(i, N + i)] = 1.0;
            for j in 0..N {
                a[(N + i, j)] = -self.k[i][j];
                a[(N + i, N + j)] = -self.damping[i][j];
            }
        }
        let mut b_force = DMatrix::<f64>::zeros(nz, N);
        for i in 0..N {
            b_force[(N + i, i)] = 1.0;
        }
        let mut b_cmd = DMatrix::<f64>::zeros(nz, N);
        let mut active: Vec<usize> = (0..nx).collect();
        for j in 0..N {
            let tau = self.lag[j];
            for i in 0..N {
                b_cmd[(N + i, j)] = self.direct[i][j];
                if tau > 0.0 {
                    // The lag state y_j (`tau y' = w_j - y`) carries the actuator's column.
                    a[(N + i, nx + j)] = self.actuation[i][j];
                } else {
                    b_cmd[(N + i, j)] += self.actuation[i][j];
                }
            }
            if tau > 0.0 {
                a[(nx + j, nx + j)] = -1.0 / tau;
                b_cmd[(nx + j, j)] = 1.0 / tau;
                active.push(nx + j);
            }
        }
        (a, b_force, b_cmd, active)
    }
}

/// A discrete law's state-space form `(A_j, B_j, C_j, d_j)` read off its difference equation
/// by stepping unit states and a unit input (the step is linear, so this is exact).
fn law_state_space(law: &Df2t) -> (DMatrix<f64>, Vec<f64>, Vec<f64>, f64) {
    let n = law.order();
    let mut probe = law.clone();
    let (mut a, mut c) = (DMatrix::<f64>::zeros(n, n), vec![0.0; n]);
    for j in 0..n {
        probe.state_mut().fill(0.0);
        probe.state_mut()[j] = 1.0;
        c[j] = probe.step(0.0);
        for (i, v) in probe.state().iter().enumerate() {
            a[(i, j)] = *v;
        }
    }
    probe.state_mut().fill(0.0);
    let d = probe.step(1.0);
    (a, probe.state().to_vec(), c, d)
}

/// The digital loop's realization at one parameter set (module doc): the plant discretised
/// under the holds, the sensing and the laws.
#[derive(Debug, Clone)]
pub struct LoopRealization<const N: usize> {
    /// Control interval `h` [s].
    pub h: f64,
    /// `Phi(h)` on the `3N` plant states, and the `3N x N` input matrices.
    pub phi: DMatrix<f64>,
    pub gam_force: DMatrix<f64>,
    pub gam_now: DMatrix<f64>,
    pub gam_prev: DMatrix<f64>,
    /// Whether there is a computation delay (the held commands are then states).
    pub delayed: bool,
    /// Indices of the plant states that exist (positions, velocities, active lags).
    pub active: Vec<usize>,
    pub s: [[f64; N]; N],
    /// One discretised law per column of `A C`, at rest.
    pub laws: Vec<Df2t>,
}

impl<const N: usize> LoopRealization<N> {
    /// The loop of `plant` with the laws `laws` at the control interval `h` and computation
    /// delay `tau` in `[0, h)`.
    pub fn new(plant: &PlantMatrices<N>, laws: Vec<Df2t>, h: f64, tau: f64) -> Self {
        let (a, b_force, b, active) = plant.continuous();
        let nz = 3 * N;
        let (phi, gam_force, gam_now, gam_prev) = if a.iter().chain(b.iter()).all(|v| v.is_finite())
        {
            let (phi, gam_force) = held_input(&a, &b_force, h);
            let (gam_now, gam_prev) = if tau > 0.0 {
                let (phi_rest, gam_rest) = held_input(&a, &b, h - tau);
                let (_, gam_tau) = held_input(&a, &b, tau);
                (gam_rest, phi_rest * gam_tau)
            } else {
                (held_input(&a, &b, h).1, DMatrix::zeros(nz, N))
            };
            (phi, gam_force, gam_now, gam_prev)
        } else {
            // Out of any physical range, where the matrix exponential's scaling would not end:
            // NaN, which `z_poles` reports naming the entry.
            let nan = |c| DMatrix::from_element(nz, c, f64::NAN);
            (nan(nz), nan(N), nan(N), nan(N))
        };
        LoopRealization {
            h,
            phi,
            gam_force,
            gam_now,
            gam_prev,
            delayed: tau > 0.0,
            active,
            s: plant.s,
            laws,
        }
    }

    /// Dimension of the loop's state: plant (with its active lag states), the controllers,
    /// and the held commands when there is a computation delay.
    pub fn state_dim(&self) -> usize {
        self.active.len()
            + self.laws.iter().map(Df2t::order).sum::<usize>()
            + if self.delayed { N } else { 0 }
    }

    /// The free loop's one-step transition matrix `M` (module doc), state order: active
    /// plant states, each law's states, the held commands.
    pub fn transition_matrix(&self) -> DMatrix<f64> {
        let (m, dim) = (self.active.len(), self.state_dim());
        // So: readouts of the active plant states (positions are the first N).
        let so = DMatrix::<f64>::from_fn(N, m, |i, c| {
            let j = self.active[c];
            if j < N {
                self.s[i][j]
            } else {
                0.0
            }
        });
        // w = -(Dso x + Cc c): rows the laws, columns the plant and controller states.
        let nc = dim - m - if self.delayed { N } else { 0 };
        let (mut dso, mut cc) = (DMatrix::<f64>::zeros(N, m), DMatrix::<f64>::zeros(N, nc));
        let mut t = DMatrix::<f64>::zeros(dim, dim);
        let mut at = 0;
        for (j, law) in self.laws.iter().enumerate() {
            let (a, b, c, d) = law_state_space(law);
            let n = law.order();
            dso.row_mut(j).copy_from(&(so.row(j) * d));
            for r in 0..n {
                cc[(j, at + r)] = c[r];
                for col in 0..m {
                    t[(m + at + r, col)] = b[r] * so[(j, col)];
                }
            }
            t.view_mut((m + at, m + at), (n, n)).copy_from(&a);
            at += n;
        }
        let sub = |g: &DMatrix<f64>| DMatrix::from_fn(m, N, |r, c| g[(self.active[r], c)]);
        let gn = sub(&self.gam_now);
        let phi = DMatrix::from_fn(m, m, |r, c| self.phi[(self.active[r], self.active[c])]);
        t.view_mut((0, 0), (m, m)).copy_from(&(phi - &gn * &dso));
        t.view_mut((0, m), (m, nc)).copy_from(&(-&gn * &cc));
        if self.delayed {
            let w = m + nc;
            t.view_mut((0, w), (m, N)).copy_from(&sub(&self.gam_prev));
            t.view_mut((w, 0), (N, m)).copy_from(&(-&dso));
            t.view_mut((w, m), (N, nc)).copy_from(&(-&cc));
        }
        t
    }

    /// The closed-loop poles in `z` (eigenvalues of [`Self::transition_matrix`]); Err names
    /// a non-finite entry or the Schur iteration that did not converge.
    pub fn z_poles(&self) -> Result<Vec<Complex64>, RootsError> {
        let m = self.transition_matrix();
        let dim = m.nrows();
        if let Some(((row, col), value)) = (0..dim)
            .flat_map(|j| (0..dim).map(move |i| (i, j)))
            .map(|ij| (ij, m[ij]))
            .find(|(_, v)| !v.is_finite())
        {
            return Err(RootsError::NonFiniteTransition {
                dim,
                row,
                col,
                value,
            });
        }
        let iterations = SCHUR_ITERATIONS_PER_STATE * dim;
        let schur = Schur::try_new(m, f64::EPSILON, iterations)
            .ok_or(RootsError::TransitionNoConvergence { dim, iterations })?;
        Ok(schur.complex_eigenvalues().iter().copied().collect())
    }

    /// The closed-loop poles as Laplace variables, `s = ln(z) / h`.
    pub fn s_poles(&self) -> Result<Vec<Complex64>, RootsError> {
        let h = self.h;
        Ok(self.z_poles()?.into_iter().map(|z| z.ln() / h).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::discrete::{DiscreteTf, Discretisation};
    use crate::model::spec::{LoopKind, ModelKind};
    use crate::model::ModelSpec;

    fn digital_x(disc: Discretisation, tau: f64) -> (LpfX, Vec<f64>) {
        let mut spec = ModelSpec::embedded_of(ModelKind::LpfX);
        spec.control_loop.kind = LoopKind::Digital;
        spec.control_loop.discretisation = disc;
        spec.control_loop.computation_delay_s = tau;
        let p = spec.scenario("monte_carlo").unwrap().truth;
        (LpfX::from_spec(&spec), p)
    }

    #[test]
    fn law_state_space_is_the_discrete_transfer_function() {
        // Oracle: the law's transfer function b(z) / a(z) (DiscreteTf::eval) against
        // C (z I - A)^-1 B + d of the state-space form read off the difference equation.
        let (x, _) = digital_x(Discretisation::Tustin, 0.0);
        let tf = &x.digital.as_ref().unwrap().c_df;
        let (a, b, c, d) = law_state_space(&Df2t::new(tf));
        let n = a.nrows();
        assert!(n > 0);
        for z in [
            Complex64::new(0.3, 0.9),
            Complex64::new(-1.2, 0.1),
            Complex64::new(2.0, -0.5),
        ] {
            let zi = DMatrix::<Complex64>::identity(n, n) * z - a.map(|v| Complex64::new(v, 0.0));
            let bz = nalgebra::DVector::from_iterator(n, b.iter().map(|v| Complex64::new(*v, 0.0)));
            let x = zi.lu().solve(&bz).unwrap();
            let got = c
                .iter()
                .zip(x.iter())
                .map(|(ci, xi)| xi * *ci)
                .sum::<Complex64>()
                + d;
            let want = tf.eval(z);
            assert!(
                (got - want).norm() < 1e-10 * want.norm(),
                "z = {z}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn x_realization_poles_are_the_x_polynomial_roots() {
        // Oracle: the digital x model's poles, the roots of its 2x2 characteristic polynomial in
        // w = z - 1 (LpfX::digital_characteristic_polynomial, a separate construction from the
        // held plant's power series): the transition matrix's eigenvalues are as many (the
        // state dimension) and each lies within 1e-8 in z of a root, for every discretisation
        // and with and without a computation delay.
        for (disc, tau) in [
            (Discretisation::Tustin, 0.0),
            (Discretisation::Tustin, 0.03),
            (Discretisation::Zoh, 0.0),
        ] {
            let (x, p) = digital_x(disc, tau);
            let h = x.digital.as_ref().unwrap().h;
            let real = x.digital_realization(&p).unwrap();
            let eig = real.z_poles().unwrap();
            let roots: Vec<Complex64> = (x.poles(&p).unwrap().iter())
                .map(|s| (s * h).exp())
                .collect();
            assert_eq!(eig.len(), roots.len(), "{disc:?} {tau}");
            assert_eq!(eig.len(), real.state_dim());
            for z in &eig {
                let nearest = (roots.iter().map(|r| (r - z).norm())).fold(f64::INFINITY, f64::min);
                assert!(
                    nearest < 1e-8,
                    "{disc:?} {tau}: eigenvalue {z} unmatched ({nearest:e})"
                );
            }
        }
    }

    #[test]
    fn a_non_finite_parameter_is_an_error_naming_the_entry() {
        // Oracle: the error's text. An infinite stiffness reaches the transition matrix as NaN
        // (the matrix exponential is not attempted) and is reported, not iterated on.
        let (x, mut p) = digital_x(Discretisation::Tustin, 0.0);
        p[crate::model::lpf_x::W1] = f64::INFINITY;
        let err = x.digital_realization(&p).unwrap().z_poles().unwrap_err();
        let text = err.to_string();
        assert!(
            text.contains("entry (0, 0)") && text.contains("not finite (NaN)"),
            "{text}"
        );
        assert!(
            matches!(err, RootsError::NonFiniteTransition { row: 0, col: 0, .. }),
            "{text}"
        );
    }

    #[test]
    fn law_state_space_of_a_zoh_lag_is_its_decay() {
        // Oracle: a first-order ZOH lag has one state; its state-space form has a = e^-ah.
        let lag = Zpk {
            gain: 1.0,
            zeros: vec![],
            poles: vec![-0.7],
        };
        let tf = DiscreteTf::from_zpk(&lag, 0.1, Discretisation::Zoh);
        let (a, _, _, _) = law_state_space(&Df2t::new(&tf));
        assert_eq!(a.nrows(), 1);
        assert!((a[(0, 0)] - (-0.07f64).exp()).abs() < 1e-15);
    }

    /// One free step of the loop from state `v` as the time-domain engine takes it (sense,
    /// command through each law's difference equation, advance the held plant, shift the
    /// held commands).
    fn probe_step<const N: usize>(r: &LoopRealization<N>, v: &[f64]) -> Vec<f64> {
        let m = r.active.len();
        let mut x = vec![0.0; 3 * N];
        for (k, &i) in r.active.iter().enumerate() {
            x[i] = v[k];
        }
        let mut laws = r.laws.clone();
        let mut at = m;
        for l in &mut laws {
            let n = l.order();
            l.state_mut().copy_from_slice(&v[at..at + n]);
            at += n;
        }
        let wp: Vec<f64> = if r.delayed {
            v[at..].to_vec()
        } else {
            vec![0.0; N]
        };
        let o: Vec<f64> = (0..N)
            .map(|i| (0..N).map(|j| r.s[i][j] * x[j]).sum())
            .collect();
        let w: Vec<f64> = (0..N).map(|j| -laws[j].step(o[j])).collect();
        let mut out: Vec<f64> = (r.active.iter())
            .map(|&i| {
                let plant: f64 = (0..3 * N).map(|j| r.phi[(i, j)] * x[j]).sum();
                plant
                    + (0..N)
                        .map(|c| r.gam_now[(i, c)] * w[c] + r.gam_prev[(i, c)] * wp[c])
                        .sum::<f64>()
            })
            .collect();
        for l in &laws {
            out.extend_from_slice(l.state());
        }
        if r.delayed {
            out.extend(w);
        }
        out
    }

    #[test]
    fn transition_matrix_is_the_probed_step() {
        // Oracle: the loop's step itself, probed column by column from unit states (what the
        // time-domain engine's transition matrix was before it was assembled here), with and
        // without a computation delay and with a lagged, damped actuator column.
        for (tau, lag) in [(0.0, 0.0), (0.03, 0.0), (0.03, 0.4)] {
            let (x, p) = digital_x(Discretisation::Tustin, tau);
            let dl = x.digital.as_ref().unwrap();
            let mut plant = PlantMatrices::of(&x, &p);
            plant.lag[0] = lag;
            plant.damping[1][1] = 1e-3 * lag;
            let laws = vec![Df2t::new(&dl.c_df), Df2t::new(&dl.c_sus)];
            let r = LoopRealization::new(&plant, laws, dl.h, tau);
            let t = r.transition_matrix();
            let dim = r.state_dim();
            assert_eq!(dim, t.nrows());
            for j in 0..dim {
                let mut e = vec![0.0; dim];
                e[j] = 1.0;
                for (i, want) in probe_step(&r, &e).into_iter().enumerate() {
                    let got = t[(i, j)];
                    assert!(
                        (got - want).abs() <= 1e-14 * want.abs().max(1.0),
                        "tau {tau}, lag {lag}: ({i}, {j}) {got:e} vs the step's {want:e}"
                    );
                }
            }
        }
    }
}
