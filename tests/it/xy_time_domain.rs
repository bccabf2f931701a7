//! The time-domain engine on the 7-DOF xy model (`sim::time_domain`, the digital loop of any
//! `DigitalPlant`: here `LpfXy`'s stiffness, sensing, actuation columns and laws). Oracles: the
//! continuous xy model's closed-loop transfer function `T_{oi->o}` (frequency-domain operator
//! algebra), which the digital loop must approach to the order of its hold and Tustin effects;
//! the frequency-domain simulator's noise-free templates; the model's closed-loop readout
//! PSD against Welch estimates of a time-domain noise run, within the estimate's statistical
//! error; a fit by the frequency-domain likelihood of time-domain data made at a control rate
//! where the continuous model describes the digital loop; the CLI's documented flags.

use freefall::io::read_parquet;
use freefall::model::spec::EMBEDDED_LPF_XY;
use freefall::model::{transfer, ClosedLoopModel};
use freefall::setup::SetupXy;
use freefall::sim::rng::stream;
use freefall::sim::time_domain::{DigitalLoop, DigitalPlant, LoopConfig};
use freefall::spectral::{welch_csd, WelchConfig};

use crate::common;
use common::freefall;
use common::loops::{measured_response, STANDARD_CYCLES, STRETCH_S};

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
    // dt1, dt12 and a_df by tens of sigmas, and the y/phi sensing cross-talk by ~20: the xy
    // model has no sampled-data form). The x block is held at the truth (its hold bias is
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
