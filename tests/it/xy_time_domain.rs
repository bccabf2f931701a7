//! The time-domain engine on the 7-DOF xy model (`sim::time_domain`, the digital loop of any
//! `DigitalPlant`: here `LpfXy`'s stiffness, sensing, actuation columns and laws). Oracles: the
//! continuous xy model's closed-loop transfer function `T_{oi->o}` (frequency-domain operator
//! algebra), which the digital loop must approach to the order of its hold and Tustin effects;
//! the frequency-domain simulator's noise-free templates; the model's closed-loop readout
//! PSD against Welch estimates of a time-domain noise run, within the estimate's statistical
//! error; a fit by the frequency-domain likelihood of time-domain data made at a control rate
//! where the continuous model describes the digital loop; the CLI's documented flags. And the
//! xy sampled-data model (`[control_loop] kind = "digital"`, `model::sampled` generic in the
//! coordinates) against the loop: its `T_{oi->o}` against steady-state sine responses, its
//! poles against the x model's in the decoupled limit and its stability against the loop's,
//! its analytic derivatives against finite differences.

use freefall::io::read_parquet;
use freefall::model::closed_loop::{transfer_with_derivatives, CMat};
use freefall::model::lpf_xy::LpfXy;
use freefall::model::spec::{LoopKind, ModelKind, EMBEDDED_LPF_XY};
use freefall::model::{transfer, ClosedLoopModel, ModelSpec};
use freefall::setup::SetupXy;
use freefall::sim::rng::stream;
use freefall::sim::time_domain::{DigitalLoop, DigitalPlant, LoopConfig};
use freefall::spectral::{welch_csd, WelchConfig};
use num_complex::Complex64;

use crate::common;
use common::freefall;
use common::loops::{measured_commands, measured_response, STANDARD_CYCLES, STRETCH_S};

/// The xy model's scenario with cross-talk in every operator (dynamical, sensing, actuation).
const SCENARIO: &str = "crosstalk";

#[test]
fn xy_sine_responses_approach_the_continuous_loop_to_the_order_of_the_hold() {
    // Oracle: the continuous xy model's T_{oi->o} (operator algebra of model::closed_loop).
    // The digital loop differs by the ZOH's half-sample delay (phase w h / 2) and Tustin's
    // warping, so every element that carries a column's response (at least 1e-2 of the
    // column's largest) must agree to 2 w h relative, and every element to 2 w h of the
    // column's largest. A wrong sign, law, actuation column, sensing row or coupling in the
    // generic plant would be an O(1) error at the lowest frequencies.
    let setup = SetupXy::embedded();
    let p = setup.spec.scenario(SCENARIO).unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    let lp = DigitalLoop::<7>::new(&setup.model, &p, &cfg);
    let delays = setup.model.guidance_delays(&p);
    for cycles in [STANDARD_CYCLES[0], STANDARD_CYCLES[6]] {
        let f = cycles / STRETCH_S;
        let wh = 2.0 * std::f64::consts::PI * f * cfg.dt;
        let t = transfer(&setup.model, &setup.model.prepare(f), &p).oi_o;
        for (c, delay) in delays.iter().enumerate() {
            let got = measured_response(&lp, f, c, *delay);
            let colmax = (0..7).map(|r| t[(r, c)].norm()).fold(0.0, f64::max);
            for (r, measured) in got.iter().enumerate() {
                let want = t[(r, c)];
                let err = (measured - want).norm();
                let bound = if want.norm() >= 1e-2 * colmax {
                    2.0 * wh * want.norm()
                } else {
                    2.0 * wh * colmax
                };
                assert!(
                    err < bound,
                    "f = {f} Hz, T[{r}][{c}]: time domain {measured:.6e}, continuous {want:.6e}, \
                     error {err:.2e} > {bound:.2e}"
                );
            }
        }
    }
}

#[test]
fn xy_noise_free_response_matches_the_frequency_domain_template() {
    // Oracle: the frequency-domain simulator's noise-free templates (zero-padded FFT of the
    // guidance through the continuous T_{oi->o}) of the design injecting on all 7 inputs. The
    // time-domain engine's noise-free telemetry (guidance at 10 Hz through the digital loop,
    // decimated by the anti-alias FIR) must agree in every readout to the order of the hold
    // at the highest injected frequency, 2 w_max h of the channel's peak, after the first
    // stretch (away from the start-up of the first injection); a readout the design leaves
    // at zero must stay there.
    let setup = SetupXy::embedded();
    let p = setup.spec.scenario(SCENARIO).unwrap().truth;
    let design = setup.design("standard_xy").unwrap();
    let td = setup
        .time_domain_simulator(&design, &p, None, None)
        .unwrap()
        .noise_free();
    let fd = setup.plain_simulator(&design, &p).unwrap().signal;
    let h = setup.spec.control_dt();
    let w_max = 2.0 * std::f64::consts::PI * STANDARD_CYCLES[6] / STRETCH_S;
    let from = (STRETCH_S / td.dt).round() as usize;
    for (e, name) in td.names.iter().enumerate() {
        for (c, (a, b)) in td.outputs[e].iter().zip(&fd[e]).enumerate() {
            let n = a.len().min(b.len());
            let peak = b[from..n].iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let worst = (from..n).map(|k| (a[k] - b[k]).abs()).fold(0.0, f64::max);
            assert!(
                worst <= 2.0 * w_max * h * peak + ZERO_RESPONSE,
                "{name}, readout {c}: worst difference {worst:.3e} of peak {peak:.3e}"
            );
        }
    }
}

/// A response this small (m or rad) is zero: a million times below the quietest readout's
/// noise in one sample.
const ZERO_RESPONSE: f64 = 1e-15;

/// Mean ratio estimate/model over bins in `[lo, hi]` and its standard error (bins treated as
/// independent with the Welch dof, inflated by 2 for the window's bin-to-bin correlation).
fn band_ratio(f: &[f64], est: &[f64], model: impl Fn(f64) -> f64, dof: f64) -> (f64, f64) {
    let r: Vec<f64> = f
        .iter()
        .zip(est)
        .filter(|(f, _)| **f >= 2e-3 && **f <= 2e-2)
        .map(|(f, e)| e / model(*f))
        .collect();
    let n = r.len() as f64;
    (
        r.iter().sum::<f64>() / n,
        (2.0 / dof).sqrt() * (2.0 / n).sqrt(),
    )
}

#[test]
fn xy_noise_run_matches_the_model_psd_of_every_readout() {
    // Oracle: the continuous xy model's closed-loop readout PSD (the frequency-domain path's
    // S_o = T S_n T^H of every noise source), against Welch estimates of a 6-hour time-domain
    // noise run decimated to 1 Hz, in [2 mHz, 20 mHz], where continuous and digital loops
    // agree to ~2 w h < 2.5e-2 (test above): each of the 7 auto-PSDs' band mean within 4 of
    // its standard errors.
    let setup = SetupXy::embedded();
    let p = setup.spec.scenario(SCENARIO).unwrap().truth;
    let design = setup
        .design("standard_xy")
        .unwrap()
        .noise_only(6.0 * 3600.0);
    let sim = setup
        .time_domain_simulator(&design, &p, None, None)
        .unwrap();
    assert!(sim.fully_supported());
    let x = sim.noise_run(&mut stream(11, 0));
    assert!(x.iter().flatten().all(|v| v.is_finite()));
    let refs: Vec<&[f64]> = x.iter().map(|c| &c[..]).collect();
    let cs = welch_csd(&refs, 1.0, &WelchConfig::default()).unwrap();
    let psd = setup.psd(&p);
    for (i, name) in setup.model.readout_names().iter().enumerate() {
        let (m, e) = band_ratio(&cs.f, &cs.psd(i), |f| psd(f)[(i, i)].re, cs.dof());
        assert!((m - 1.0).abs() < 4.0 * e, "{name}: ratio {m} +- {e}");
    }
}

#[test]
fn xy_fit_of_time_domain_data_recovers_the_truth() {
    // Oracle: the truth of the simulation. Time-domain data of the xy loop fitted by the
    // frequency-domain (continuous) xy likelihood: an independent path from the engine's
    // matrix exponentials and difference equations. The continuous model describes the
    // digital loop to O(w h), so the loop runs at 100 Hz (h = 0.01 s; at 10 Hz the hold biases
    // dt1, dt12 and a_df by tens of sigmas, and the y/phi sensing cross-talk by ~20, which is
    // why a 10 Hz time-domain campaign fits the sampled-data model). The x block is held at the truth (its hold bias is
    // still 3-7 sigma at 100 Hz), as are the actuation coefficients the campaign
    // xy_crosstalk.toml fixes; every other parameter must lie within 3 sigma of the truth.
    let tmp = tempfile::tempdir().unwrap();
    let model = tmp.path().join("xy100.toml");
    let text = EMBEDDED_LPF_XY.replacen("simulate_hz = 10.0", "simulate_hz = 100.0", 1);
    assert_ne!(
        text, EMBEDDED_LPF_XY,
        "the embedded file's simulate_hz line moved"
    );
    std::fs::write(&model, text).unwrap();
    let (ds, out) = (tmp.path().join("ds"), tmp.path().join("fit"));
    let m = model.to_str().unwrap();
    common::ok(&[
        "--quiet",
        "simulate",
        "--model",
        m,
        "--scenario",
        "sensing_crosstalk",
        "--design",
        "standard_xy",
        "--seed",
        "4",
        "--engine",
        "time-domain",
        "--out",
        ds.to_str().unwrap(),
    ]);
    let setup = SetupXy::embedded();
    let truth = setup.spec.scenario("sensing_crosstalk").unwrap().truth;
    let names = setup.parameter_names();
    let fixed: Vec<String> = names[..7]
        .iter()
        .zip(&truth)
        .map(|(n, v)| format!("{n}={v:e}"))
        .chain(
            [
                "d_df_ysc",
                "d_sus_y1",
                "d_sus_y2",
                "d_sus_phi1",
                "d_sus_phi2",
            ]
            .map(String::from),
        )
        .collect();
    let mut args = vec!["--quiet", "fit", "--model", m];
    for f in &fixed {
        args.extend(["--fix", f]);
    }
    let dataset = ds.join("dataset.toml");
    args.extend([dataset.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    common::ok(&args);
    let t = read_parquet(out.join("estimates.parquet")).unwrap();
    let (est, sigma) = (
        t.f64_column("estimate").unwrap(),
        t.f64_column("sigma").unwrap(),
    );
    let mut free = 0;
    for (k, name) in names.iter().enumerate() {
        if sigma[k] == 0.0 {
            continue;
        }
        free += 1;
        let pull = (est[k] - truth[k]) / sigma[k];
        assert!(
            pull.abs() < 3.0,
            "{name}: {} vs truth {} ({pull:.2} sigma)",
            est[k],
            truth[k]
        );
    }
    assert_eq!(free, names.len() - fixed.len());
}

#[test]
fn cli_simulates_the_xy_loop_in_the_time_domain_with_initial_conditions() {
    // Oracle: the documented flags. `--engine time-domain` on lpf_xy writes the runs with the
    // other readouts and guidance as auxiliary columns and names engine, rate and every
    // readout's initial position and rate in [meta]; a key that is no xy readout is a
    // one-line error listing the keys; `fit --transient` on the dataset reports the 14
    // initial conditions of each run, and finds the given start in the experiments.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("td");
    common::ok(&[
        "--quiet",
        "simulate",
        "--model",
        "lpf_xy",
        "--scenario",
        "crosstalk",
        "--engine",
        "time-domain",
        "--initial",
        "o1=2.4e-7,oy1=3e-7,vphi1=-2e-9",
        "--noise-duration",
        "21600",
        "--out",
        out.to_str().unwrap(),
    ]);
    let meta: toml::Table =
        toml::from_str(&std::fs::read_to_string(out.join("dataset.toml")).unwrap()).unwrap();
    let aux = meta["auxiliary"].as_array().unwrap();
    assert_eq!(
        aux.len(),
        10,
        "5 readouts and 5 guidance inputs beyond o1, o12"
    );
    let meta = meta["meta"].as_table().unwrap();
    assert_eq!(meta["engine"].as_str(), Some("time-domain"));
    assert_eq!(meta["rate"].as_str(), Some("decimated"));
    let initial = meta["initial"].as_table().unwrap();
    assert_eq!(initial.len(), 14);
    assert_eq!(initial["oy1"].as_float(), Some(3e-7));
    assert_eq!(initial["vphi1"].as_float(), Some(-2e-9));
    assert_eq!(initial["vphisc"].as_float(), Some(0.0));
    let o = freefall(&[
        "simulate",
        "--model",
        "lpf_xy",
        "--engine",
        "time-domain",
        "--scenario",
        "crosstalk",
        "--initial",
        "v3=1",
        "--out",
        dir.path().join("bad").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(
        err.contains("unknown key 'v3'") && err.contains("vphisc"),
        "{err}"
    );
    // The standard design injects along x only: the other parameters are held at the guess.
    let fit = dir.path().join("fit");
    let setup = SetupXy::embedded();
    let dataset = out.join("dataset.toml");
    let names = setup.parameter_names();
    let mut args = vec![
        "fit",
        "--model",
        "lpf_xy",
        "--transient",
        dataset.to_str().unwrap(),
    ];
    for n in &names[7..] {
        args.extend(["--fix", n.as_str()]);
    }
    args.extend(["--out", fit.to_str().unwrap()]);
    let o = common::ok(&args);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fit.join("fit.json")).unwrap()).unwrap();
    let runs = json["transients"].as_array().unwrap();
    assert_eq!(runs.len(), 3, "noise run, exp1, exp2");
    for r in runs {
        assert_eq!(r["initial_conditions"].as_array().unwrap().len(), 14);
    }
    assert!(runs[1]["significant"].as_bool().unwrap(), "{}", runs[1]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("transient exp1") && text.contains("oy1 = "),
        "{text}"
    );
}

/// The embedded xy model made digital (Tustin laws) with computation delay `tau`
/// (campaigns/models/lpf_xy_digital.toml is the `tau = 0` one).
fn digital_xy(tau: f64) -> SetupXy {
    let mut spec = ModelSpec::embedded_of(ModelKind::LpfXy);
    spec.control_loop.kind = LoopKind::Digital;
    spec.control_loop.computation_delay_s = tau;
    SetupXy::new(spec).unwrap()
}

/// Agreement required between the time-domain loop and the xy sampled-data model, relative to
/// an element (or to its column's largest for elements below 1e-2 of it).
const XY_ENGINE_AGREEMENT: f64 = 1e-6;

#[test]
fn xy_sine_responses_match_the_sampled_data_model() {
    // Oracle: T_{oi->o} of the digital xy model (model::sampled's held plant D_d(z) and delay
    // factor H(z), the laws at z = exp(i w h)), which the time-domain loop (matrix
    // exponentials and difference equations, a separate implementation) must reproduce in
    // steady state, every element of every column, to 1e-6 of the element (or of the column's
    // largest where the element is below 1e-2 of it): where the continuous model differs by
    // the hold's O(w h), the sampled-data model is exact.
    for (tau, cycles) in [
        (0.0, STANDARD_CYCLES[0]),
        (0.0, STANDARD_CYCLES[6]),
        (0.03, STANDARD_CYCLES[3]),
    ] {
        let setup = digital_xy(tau);
        let p = setup.spec.scenario(SCENARIO).unwrap().truth;
        let lp = DigitalLoop::<7>::new(&setup.model, &p, &LoopConfig::from_spec(&setup.spec));
        let delays = setup.model.guidance_delays(&p);
        let f = cycles / STRETCH_S;
        let t = transfer(&setup.model, &setup.model.prepare(f), &p).oi_o;
        for (c, delay) in delays.iter().enumerate() {
            let got = measured_response(&lp, f, c, *delay);
            let colmax = (0..7).map(|r| t[(r, c)].norm()).fold(0.0, f64::max);
            for (r, measured) in got.iter().enumerate() {
                let want = t[(r, c)];
                let scale = want.norm().max(1e-2 * colmax);
                let err = (measured - want).norm();
                assert!(
                    err < XY_ENGINE_AGREEMENT * scale,
                    "tau {tau}, f = {f} Hz, T[{r}][{c}]: time domain {measured:.9e}, \
                     sampled-data model {want:.9e}, error {:.1e} of {scale:.2e}",
                    err / scale
                );
            }
        }
    }
}

#[test]
fn xy_sampled_data_poles_contain_the_x_poles_when_decoupled() {
    // Oracle: the digital x model's poles, the roots of its 2x2 characteristic polynomial in
    // w = z - 1 (which the x loop's eigenvalues match, time_domain::
    // sampled_data_poles_are_the_simulated_loop_eigenvalues). With every cross-talk coefficient
    // zero (scenario nominal) the xy loop is the x loop beside the y and phi loops, so the xy
    // model's poles (eigenvalues of the 7-DOF loop's transition matrix, model::sampled_loop)
    // contain every x pole, to 1e-8 in z; they are as many as the loop's states; and the
    // loop is stable, as the time-domain loop's own check finds.
    for tau in [0.0, 0.03] {
        let setup = digital_xy(tau);
        let p = setup.spec.scenario("nominal").unwrap().truth;
        let h = setup.spec.control_dt();
        let to_z = |s: &Complex64| (s * h).exp();
        let xy: Vec<Complex64> = setup.model.poles(&p).unwrap().iter().map(to_z).collect();
        let x: Vec<Complex64> = setup
            .model
            .x
            .poles(&p[..7])
            .unwrap()
            .iter()
            .map(to_z)
            .collect();
        let lp = DigitalLoop::<7>::new(&setup.model, &p, &LoopConfig::from_spec(&setup.spec));
        assert_eq!(xy.len(), lp.state_dim(), "tau {tau}");
        assert!(x.len() < xy.len(), "tau {tau}: {} x poles", x.len());
        for z in &x {
            let nearest = xy
                .iter()
                .map(|m| (m - z).norm())
                .fold(f64::INFINITY, f64::min);
            assert!(
                nearest < 1e-8,
                "tau {tau}: x pole {z} not an xy pole ({nearest:e})"
            );
        }
        freefall::model::check_stability(&setup.model, &p, None).unwrap();
        lp.check_stable(setup.model.parameter_names(), &p).unwrap();
    }
}

#[test]
fn xy_sampled_data_stability_accepts_the_stable_crosstalk_scenarios() {
    // Oracle: the time-domain loop's stability (every eigenvalue of its one-step transition
    // matrix inside the unit circle, which the loop's sine responses settling confirm in
    // xy_sine_responses_match_the_sampled_data_model) and the continuous xy model's stability
    // check of the same parameters. The digital model's check must agree on the cross-talk
    // scenarios: before its poles came from the transition matrix, the roots of the expanded
    // 7x7 determinant put a spurious pole at s = +1.75e-6 rad/s and refused sensing_crosstalk.
    let continuous = SetupXy::embedded();
    for tau in [0.0, 0.03] {
        let setup = digital_xy(tau);
        for scenario in ["sensing_crosstalk", "actuation_crosstalk", SCENARIO] {
            let p = setup.spec.scenario(scenario).unwrap().truth;
            freefall::model::check_stability(&continuous.model, &p, None).unwrap();
            let lp = DigitalLoop::<7>::new(&setup.model, &p, &LoopConfig::from_spec(&setup.spec));
            lp.check_stable(setup.model.parameter_names(), &p).unwrap();
            freefall::model::check_stability(&setup.model, &p, None)
                .unwrap_or_else(|e| panic!("tau {tau}, {scenario}: {e}"));
        }
    }
}

#[test]
fn xy_loop_commands_match_the_frequency_domain_commands() {
    // Oracle: the frequency-domain engine's commands (sim::commands::command_response's kernel
    // -C_j (T_{oi->o} - 1)[j][c], here of the digital xy model, exact at the control samples).
    // The time-domain loop's recorded commands of the y/phi loops (DigitalLoop::run_recording,
    // what `simulate --engine time-domain --commands` decimates) under a unit sine on each y/phi
    // guidance input, in steady state, agree to XY_ENGINE_AGREEMENT of the command (or of the
    // input's largest command where a command is below 1e-2 of it).
    let setup = digital_xy(0.03);
    let p = setup.spec.scenario(SCENARIO).unwrap().truth;
    let lp = DigitalLoop::<7>::new(&setup.model, &p, &LoopConfig::from_spec(&setup.spec));
    let record: Vec<usize> = (2..7).collect();
    let f = STANDARD_CYCLES[3] / STRETCH_S;
    let pt = setup.model.prepare(f);
    let t = transfer(&setup.model, &pt, &p).oi_o;
    for c in 2..7 {
        let got = measured_commands(&lp, f, c, &record);
        let want: Vec<Complex64> = (record.iter())
            .map(|&j| {
                let e = t[(j, c)] - if j == c { 1.0 } else { 0.0 };
                -LpfXy::law_at(&pt, j) * e
            })
            .collect();
        let largest = want.iter().map(|w| w.norm()).fold(0.0, f64::max);
        for ((j, g), w) in record.iter().zip(&got).zip(&want) {
            let scale = w.norm().max(1e-2 * largest);
            let err = (g - w).norm() / scale;
            assert!(
                err < XY_ENGINE_AGREEMENT,
                "u{j} under oi{c}: time domain {g:.9e}, frequency domain {w:.9e}, error {err:.1e}"
            );
        }
    }
}

#[test]
fn xy_sampled_data_derivatives_match_central_differences() {
    // Oracle: central finite differences of the digital xy model's T_{oi->o}, step 1e-5 of
    // each parameter's scale (the stiffness and dynamical cross-talk parameters move the held
    // plant's matrix functions of K; the others enter as in the continuous model, behind the
    // delay factor); and the grid path (held plant once) against the per-point path.
    let setup = digital_xy(0.03);
    let m = &setup.model;
    let p = setup.spec.scenario(SCENARIO).unwrap().truth;
    let np = p.len();
    let scale = |k: usize| match setup.parameter_names()[k].as_str() {
        n if n.starts_with('w') => 1e-6,
        n if n.starts_with('a') => 1.0,
        n if n.starts_with("dt") => 0.1,
        _ => 1e-3,
    };
    let freqs = [3e-5, 1e-3, 2e-2, 0.3];
    let points: Vec<_> = freqs.iter().map(|&f| m.prepare(f)).collect();
    let mut t_grid = vec![CMat::<7>::zeros(); freqs.len()];
    let mut d_grid = vec![CMat::<7>::zeros(); np * freqs.len()];
    m.transfer_grid(&points, &p, &mut t_grid, Some(&mut d_grid));
    for (i, pt) in points.iter().enumerate() {
        let mut d = vec![CMat::<7>::zeros(); np];
        let t = transfer_with_derivatives(m, pt, &p, &mut d).oi_o;
        assert!((t - t_grid[i]).norm() <= 1e-12 * t.norm());
        for k in 0..np {
            assert!((d[k] - d_grid[np * i + k]).norm() <= 1e-12 * d[k].norm() + 1e-300);
            let step = 1e-5 * scale(k);
            let (mut pp, mut pm) = (p.clone(), p.clone());
            pp[k] += step;
            pm[k] -= step;
            let fd = (transfer(m, pt, &pp).oi_o - transfer(m, pt, &pm).oi_o)
                / Complex64::new(2.0 * step, 0.0);
            // Truncation O(step^2) plus round-off O(eps |T| / step), relative to |T| / scale.
            let err = (fd - d[k]).norm();
            assert!(
                err <= 1e-6 * t.norm() / scale(k) + 1e-7 * d[k].norm(),
                "{} at f = {}: analytic {:.3e} vs fd {:.3e}",
                setup.parameter_names()[k],
                freqs[i],
                d[k].norm(),
                fd.norm()
            );
        }
    }
}
