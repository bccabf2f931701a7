//! Auxiliary readouts of other degrees of freedom in simulated data, and their sensing
//! cross-talk into the optical readouts (thesis sec. 3.4, "Cross-talk from degrees of freedom
//! other than the optical axis").
//!
//! Each auxiliary channel of the model file (`[auxiliary.COLUMN]`) is drawn as colored
//! Gaussian noise of its ASD ([`crate::model::spec::AuxiliarySpec`]), independently of the
//! optical noise: experiments from stream (seed, [`AUX_STREAM`]), the noise run from stream
//! (seed, [`AUX_STREAM`] + 1), so that adding auxiliary channels leaves the readouts of a seed
//! unchanged.
//!
//! A sensing cross-talk leaks `k a(t) + k' da/dt` of the recorded series `a` (a static
//! coefficient and a first-derivative term, [`rate`]) into the sensor of o1 or o12, of every
//! run, noise run included. The sensor is inside the loop: o1 is the drag-free error signal,
//! o12 the suspension's. With `o_x = S q_x + delta_S a + n` the dynamics
//! `D q_x = f - A C (o_x - o_i)` give `Delta o_x = ... + D S^-1 delta_S a`, so the leak reaches
//! the recorded readouts as `Delta^-1 D S^-1 e_c (k a + k' da/dt)` ([`in_loop`]): suppressed by
//! the loop in its band, additive above it (thesis sec. 3.4, the readout-noise cross-talk
//! operator). The xy model (sec. 3.5) simulates the same physics with the auxiliary degrees of
//! freedom in its loop, an independent path (`tests/it/xy_diagnose.rs`).
//!
//! A force cross-talk leaks `k u(t)` of a recorded command `u` (the acceleration another
//! degree of freedom's loop asks its actuator for) into the acceleration of x1 or x12, the
//! row of `Delta o_x = g + ...` it acts on (thesis sec. 3.5, the actuation cross-talk
//! `delta A C0`): it reaches the readouts as `Delta^-1 e_c k u` ([`Leak::Force`]).

use crate::data::{AuxChannel, Auxiliary, ExperimentData};
use crate::model::closed_loop::{transfer, CMat, ClosedLoopModel};
use crate::model::spec::ModelSpec;
use crate::noise::generate::ColoredNoise;
use crate::noise::NoiseError;
use crate::numerics::fft::filter_padded;
use crate::sim::rng::stream;

/// Stream index of the experiments' auxiliary series (the noise run's is the next one);
/// streams 0 and 1 are the experiments' and the noise run's optical noise.
pub const AUX_STREAM: u64 = 2;
/// Length factor of the generated series over the requested one (as the optical noise).
const OVERSAMPLE: usize = crate::noise::NOISE_OVERSAMPLE;

/// The first derivative of a uniformly sampled series by central differences (one-sided at
/// the ends): the template of a rate (first-derivative) cross-talk term, the same in the
/// simulation and in the fit. Its response is `i sin(omega dt) / dt`, `i omega` to
/// `(omega dt)^2 / 6` relative.
pub fn rate(x: &[f64], dt: f64) -> Vec<f64> {
    let n = x.len();
    if n < 2 {
        return vec![0.0; n];
    }
    (0..n)
        .map(|i| match i {
            0 => (x[1] - x[0]) / dt,
            _ if i == n - 1 => (x[n - 1] - x[n - 2]) / dt,
            _ => (x[i + 1] - x[i - 1]) / (2.0 * dt),
        })
        .collect()
}

/// A sensing cross-talk from auxiliary column `column` into readout `channel` (0: o1, 1: o12):
/// `o += coefficient a + rate d a/dt` (coefficient in m/m or m/rad, rate in those per s^-1).
#[derive(Debug, Clone, PartialEq)]
pub struct Crosstalk {
    pub column: String,
    pub channel: usize,
    pub coefficient: f64,
    pub rate: f64,
}

/// Draws every auxiliary channel of `spec` over experiments of `lengths` samples and a noise
/// run of `noise_len` samples at `dt`.
pub fn draw(
    spec: &ModelSpec,
    lengths: &[usize],
    noise_len: usize,
    dt: f64,
    seed: u64,
) -> Result<Auxiliary, NoiseError> {
    let channels: Vec<AuxChannel> = spec
        .auxiliary
        .iter()
        .map(|(name, a)| AuxChannel {
            column: name.clone(),
            kind: a.kind,
            unit: a.kind.unit().to_string(),
            role: if a.kind.is_command() {
                crate::data::AuxRole::Command
            } else {
                crate::data::AuxRole::Readout
            },
            noise_asd: None,
        })
        .collect();
    let series = |n: usize, rng: &mut rand_xoshiro::Xoshiro256PlusPlus| {
        spec.auxiliary
            .values()
            .map(|a| {
                let src = a.source();
                let psd = |f: f64| {
                    let mut m = crate::model::closed_loop::CMat::<1>::zeros();
                    m[(0, 0)] = crate::noise::shapes::psd(&src, f).into();
                    m
                };
                let g = ColoredNoise::<1>::new(psd, n, dt, OVERSAMPLE)?;
                Ok(g.generate(rng).swap_remove(0))
            })
            .collect::<Result<Vec<Vec<f64>>, NoiseError>>()
    };
    let mut rng = stream(seed, AUX_STREAM);
    let experiments = lengths
        .iter()
        .map(|&n| series(n, &mut rng))
        .collect::<Result<Vec<_>, _>>()?;
    let noise = series(noise_len, &mut stream(seed, AUX_STREAM + 1))?;
    Ok(Auxiliary {
        channels,
        experiments,
        noise: Some(noise),
    })
}

/// Where a cross-talk enters the x loop (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Leak {
    /// Into the sensor of a readout: `Delta^-1 D S^-1 e_c`.
    Sensor,
    /// Into the acceleration of a coordinate: `Delta^-1 e_c`.
    Force,
}

/// The response of the two readouts to a leak `x(t)` into the sensor of readout `channel`
/// (0: o1, 1: o12) of `model` at `p`: `Delta^-1 D S^-1 e_channel x` (module doc), by FFT with
/// zero padding to at least twice the length (a linear, not circular, filter; the loop starts
/// from rest at the first sample).
pub fn in_loop<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    p: &[f64],
    x: &[f64],
    channel: usize,
    dt: f64,
) -> [Vec<f64>; N] {
    through_loop(model, p, x, channel, Leak::Sensor, dt)
}

/// The response of the two readouts to a leak `x(t)` entering the x loop of `model` at `p`
/// at `leak` of row `channel` (0: o1 / x1, 1: o12 / x12): `Delta^-1 D S^-1 e_channel x` for a
/// sensing, `Delta^-1 e_channel x` for a force cross-talk, by FFT with zero padding to at
/// least twice the length (a linear, not circular, filter; the loop starts from rest at the
/// first sample). For a model of `N` readouts the response is that of all `N`, row
/// `channel` the readout (or coordinate) it enters.
pub fn through_loop<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    p: &[f64],
    x: &[f64],
    channel: usize,
    leak: Leak,
    dt: f64,
) -> [Vec<f64>; N] {
    // The loop's response per bin; the DC bin takes its limit at low frequency (D has s^2,
    // Delta^-1 finite).
    let df = 1.0 / ((2 * x.len()).next_power_of_two() as f64 * dt);
    filter_padded(x, dt, |_, f| {
        let f = if f == 0.0 { 1e-3 * df } else { f };
        let tr = transfer(model, &model.prepare(f), p);
        let h = match leak {
            Leak::Sensor => {
                let s_inv = tr.ops.s.try_inverse().unwrap_or_else(CMat::<N>::identity);
                tr.delta_inv * tr.ops.d * s_inv
            }
            Leak::Force => tr.delta_inv,
        };
        std::array::from_fn(|r| h[(r, channel)])
    })
}

/// Adds each cross-talk of `leaks`, through the loop of `model` at `p` ([`in_loop`]), to the
/// readouts of the experiments `data` and of the noise run `noise`, from the recorded series
/// `aux`. Errors name a column `aux` does not have.
pub fn apply<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    p: &[f64],
    aux: &Auxiliary,
    leaks: &[Crosstalk],
    data: &mut ExperimentData,
    noise: &mut [Vec<f64>],
) -> Result<(), String> {
    let dt = data.dt;
    for l in leaks {
        let k = aux
            .channels
            .iter()
            .position(|c| c.column == l.column)
            .ok_or_else(|| {
                let known: Vec<&str> = aux.channels.iter().map(|c| c.column.as_str()).collect();
                format!(
                    "aux_crosstalk_{}: no auxiliary channel '{}' in the model file (known: {})",
                    l.column,
                    l.column,
                    known.join(", ")
                )
            })?;
        let add = |o: &mut [Vec<f64>], a: &[f64]| {
            let da = rate(a, dt);
            let leak: Vec<f64> = a
                .iter()
                .zip(&da)
                .map(|(a, d)| l.coefficient * a + l.rate * d)
                .collect();
            for (o, r) in o.iter_mut().zip(in_loop(model, p, &leak, l.channel, dt)) {
                for (o, r) in o.iter_mut().zip(r) {
                    *o += r;
                }
            }
        };
        for (e, out) in data.outputs.iter_mut().enumerate() {
            if let Some(a) = aux.experiments.get(e).and_then(|x| x.get(k)) {
                add(out, a);
            }
        }
        if let Some(a) = aux.noise.as_ref().and_then(|x| x.get(k)) {
            add(noise, a);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn in_loop_leak_is_additive_above_the_loop_and_suppressed_below() {
        // Oracle: Delta^-1 D S^-1 -> 1 where the control is negligible (far above the
        // suspension's unity gain, ~1 mHz), and the steady-state response of a sine is the
        // transfer at its frequency.
        let setup = crate::setup::Setup::embedded_continuous();
        let p = setup.spec.nominal();
        let (dt, n) = (1.0, 8192);
        for (f, tol) in [(0.2, 0.02), (1.0 / 1024.0, f64::INFINITY)] {
            let w = 2.0 * std::f64::consts::PI * f;
            let x: Vec<f64> = (0..n).map(|i| (w * i as f64 * dt).sin()).collect();
            let y = in_loop(&setup.model, &p, &x, 1, dt);
            let tail = &y[1][n / 2..];
            let amp = (2.0 * tail.iter().map(|v| v * v).sum::<f64>() / tail.len() as f64).sqrt();
            let tr = transfer(&setup.model, &setup.model.prepare(f), &p);
            let h = tr.delta_inv * tr.ops.d * tr.ops.s.try_inverse().unwrap();
            assert!(
                (amp / h[(1, 1)].norm() - 1.0).abs() < 1e-2,
                "f {f}: {amp} vs {}",
                h[(1, 1)].norm()
            );
            assert!((amp - 1.0).abs() < tol, "f {f}: amplitude {amp}");
        }
    }

    #[test]
    fn rate_of_a_sine_is_the_central_difference_response() {
        // Oracle: analytic; the central difference of sin(w t) is w cos(w t) sin(w dt)/(w dt).
        let (dt, w) = (1.0, 2.0 * std::f64::consts::PI * 0.05);
        let x: Vec<f64> = (0..200).map(|i| (w * i as f64 * dt).sin()).collect();
        let d = rate(&x, dt);
        for (i, v) in d.iter().enumerate().take(199).skip(1) {
            let expected = w * (w * i as f64 * dt).cos() * (w * dt).sin() / (w * dt);
            assert!((v - expected).abs() < 1e-12, "sample {i}");
        }
    }

    #[test]
    fn crosstalk_adds_the_recorded_series_through_the_loop_to_every_run() {
        // Oracle: the definition, the loop's response to k a + k' da/dt entering the sensor of
        // o12, in the experiments and the noise run.
        let spec = ModelSpec::embedded();
        let setup = crate::setup::Setup::embedded();
        let p = spec.nominal();
        let aux = draw(&spec, &[64, 80], 100, 1.0, 7).unwrap();
        let k = aux.channels.iter().position(|c| c.column == "oy1").unwrap();
        let mut data = ExperimentData {
            tails: Vec::new(),
            names: vec!["a".into(), "b".into()],
            inputs: vec![vec![vec![0.0; 64]; 2], vec![vec![0.0; 80]; 2]],
            outputs: vec![vec![vec![0.0; 64]; 2], vec![vec![0.0; 80]; 2]],
            dt: 1.0,
        };
        let mut noise = vec![vec![0.0; 100]; 2];
        let leak = Crosstalk {
            column: "oy1".into(),
            channel: 1,
            coefficient: -3e-3,
            rate: 2e-3,
        };
        let m = &setup.model;
        apply(
            m,
            &p,
            &aux,
            std::slice::from_ref(&leak),
            &mut data,
            &mut noise,
        )
        .unwrap();
        let expect = |a: &[f64]| -> [Vec<f64>; 2] {
            let d = rate(a, 1.0);
            let leak: Vec<f64> = a
                .iter()
                .zip(&d)
                .map(|(x, v)| -3e-3 * x + 2e-3 * v)
                .collect();
            in_loop(m, &p, &leak, 1, 1.0)
        };
        assert_eq!(data.outputs[1], expect(&aux.experiments[1][k]).to_vec());
        assert_eq!(noise, expect(&aux.noise.as_ref().unwrap()[k]).to_vec());
        assert!(data.outputs[0][1].iter().any(|v| *v != 0.0));
        let bad = Crosstalk {
            column: "oz9".into(),
            ..leak
        };
        let e = apply(m, &p, &aux, &[bad], &mut data, &mut noise).unwrap_err();
        assert!(e.contains("'oz9'") && e.contains("oy1"), "{e}");
    }
}
