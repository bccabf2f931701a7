//! Total equivalent acceleration through Delta(p) (thesis sec. 3.1 eq. "ifo2acc", 4.6).
//! Each test names its oracle.

use std::f64::consts::PI;

use freefall::accel::{
    budget, budget_of_telemetry, derivative::PI_STENCIL, projection, projection_of_telemetry,
    welch_psd, AccelPsd, DeltaEstimator, Response, Stencil,
};
use freefall::noise::ColoredNoise;
use freefall::noise::NOISE_OVERSAMPLE;
use freefall::setup::Setup;
use freefall::sim::rng::stream;
use freefall::spectral::WelchConfig;
use num_complex::Complex64;

use crate::common;
use common::loops::digital_setup;
use common::{freefall, ok};
use std::process::Output;

/// Analysis sampling interval of the reference model (1 Hz).
const DT: f64 = 1.0;
/// Six days at 1 Hz (thesis sec. 4.6: "a very long noise run, ~6 days").
const SIX_DAYS: usize = 6 * 86_400;
/// Confidence level of the bands (the 90 %).
const LEVEL: f64 = 0.9;

fn noise_run(setup: &Setup, truth: &[f64], n: usize, seed: u64) -> Vec<Vec<f64>> {
    let gen = ColoredNoise::new(setup.psd(truth), n, DT, NOISE_OVERSAMPLE).unwrap();
    gen.generate(&mut stream(seed, 0))
}

/// Oracle: analytic. The stencil differentiates a quadratic exactly, and a sampled sinusoid is
/// multiplied by its response `[2a cos 2x + 2b cos x + c] / dt^2` (x = w dt), which for the "pi"
/// estimator is `-sin^2(x) / dt^2`.
#[test]
fn stencil_is_exact_on_quadratics_and_has_its_response_on_sines() {
    for a in [PI_STENCIL, 2.0 / 7.0, -1.0 / 12.0] {
        let st = Stencil::new(a).unwrap();
        let dt = 0.5;
        let x: Vec<f64> = (0..20)
            .map(|k| {
                let t = k as f64 * dt;
                3.0 * t * t - 2.0 * t + 1.0
            })
            .collect();
        let mut out = vec![0.0; x.len() - 4];
        st.accumulate(&x, dt, 1.0, &mut out);
        assert!(
            out.iter().all(|v| (v - 6.0).abs() < 1e-9),
            "a = {a}: {out:?}"
        );
        let f = 0.13;
        let h = st.response(f, dt);
        let x: Vec<f64> = (0..40)
            .map(|k| (2.0 * PI * f * k as f64 * dt + 0.3).sin())
            .collect();
        let mut out = vec![0.0; x.len() - 4];
        st.accumulate(&x, dt, 1.0, &mut out);
        for (k, v) in out.iter().enumerate() {
            assert!((v - h * x[k + 2]).abs() < 1e-12, "a = {a}, sample {k}");
        }
    }
    let w = 2.0 * PI * 0.13 * 0.5;
    let pi = Stencil::default().response(0.13, 0.5);
    assert!((pi + (w.sin() / 0.5).powi(2)).abs() < 1e-12);
    assert!(Stencil::new(f64::NAN).is_err());
}

/// Oracle: frequency response. A sinusoidal readout (or guidance) series converted by the
/// estimator equals `Re[Delta_h(f) e^{iwt}]` (or `-Re[A C T(f) e^{iwt}]`) away from the ends,
/// where `Delta_h` is the estimator's response; this checks the time-domain stencil, the
/// running-sum integrator and the padded FFT convolution together. Below 10 mHz `Delta_h`
/// agrees with the model's continuous `Delta` to (w dt)^2 / 3. Checked for the continuous
/// loop and for the digital one, whose held plant adds the third-derivative stencil.
#[test]
fn time_domain_estimate_follows_the_frequency_response() {
    for setup in [Setup::embedded_continuous(), digital_setup()] {
        follows_the_frequency_response(&setup);
    }
}

fn follows_the_frequency_response(setup: &Setup) {
    let p = setup.spec.scenario("under_performing").unwrap().truth;
    let est = DeltaEstimator::new(&setup.model, &p, DT, Stencil::default()).unwrap();
    let n = 40_000;
    // A whole number of cycles is not needed: the FFT part is a linear convolution.
    for f in [3.1e-4, 2.7e-3, 4.9e-2, 0.21] {
        let resp = est.response(f);
        let cont = est.continuous(f);
        if f < 1e-2 {
            let rel = (resp - cont).norm() / cont.norm();
            assert!(
                rel < (2.0 * PI * f * DT).powi(2),
                "f = {f}: |Delta_h - Delta| = {rel:e}"
            );
        }
        for input in 0..2 {
            let x: Vec<f64> = (0..n)
                .map(|k| (2.0 * PI * f * k as f64 * DT).cos())
                .collect();
            let zero = vec![0.0; n];
            let mut o = [zero.as_slice(), zero.as_slice()];
            o[input] = &x;
            let g = est.apply(o, None).unwrap();
            // Compare the mean-free middle halves (the running sum's start constant is unknown).
            for ch in 0..2 {
                let mid = |v: &dyn Fn(usize) -> f64| -> Vec<f64> {
                    let s: Vec<f64> = (n / 4..3 * n / 4).map(v).collect();
                    let m = s.iter().sum::<f64>() / s.len() as f64;
                    s.iter().map(|x| x - m).collect()
                };
                let got = mid(&|k| g[ch][k - est.edge()]);
                let want = mid(&|k| {
                    let e = Complex64::new(0.0, 2.0 * PI * f * k as f64 * DT).exp();
                    (resp[(ch, input)] * e).re
                });
                let scale = resp[(ch, input)].norm();
                let err = got
                    .iter()
                    .zip(&want)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                // The FFT part applies the continuous control laws up to Nyquist; where a law
                // does not vanish there its kernel has 1/(pi d) tails, and the abrupt start and
                // end of the series leak in by at most |R(f_Nyquist)| / (pi d), d >= n / 4 = 1e4
                // samples here: 3.2e-5 |R|, bounded by 1e-4 |R|.
                let tail = est.multipliers(0.5 / DT).0[(ch, input)].norm();
                assert!(
                    err <= 1e-9 * scale + 1e-4 * tail,
                    "{}: f = {f}, readout {input} -> g{ch}: max error {err:e} vs |Delta_h| {scale:e}",
                    setup.spec.origin
                );
            }
        }
    }
}

/// Oracle: the closed loop's own algebra (thesis eq. "equation of motion in the sensed
/// coordinates"). The noise-free response to guidance injections, `o = Delta^-1 A C T o_i`
/// (templates of the identification experiments), converts to zero acceleration at the true
/// parameters: `Delta o - A C T o_i = 0`, up to the discrete derivative's `(H - s^2) o`, which is
/// at most `(w dt)^2 / 3` of the inertia term at the injections' highest frequency.
#[test]
fn guidance_injections_leave_no_acceleration_at_the_true_parameters() {
    use freefall::forward::TemplateEngine;
    let setup = Setup::embedded_continuous(); // the thesis's loop
    let p = setup.spec.scenario("under_performing").unwrap().truth;
    let design = setup.design("standard").unwrap();
    let n = design.samples(DT);
    let inputs: Vec<Vec<Vec<f64>>> = (0..design.experiments.len())
        .map(|e| design.sample(e, 2, 0.0, DT, n))
        .collect();
    let engine = TemplateEngine::new(&setup.model, &inputs, DT);
    let outputs = engine.templates(&p, None);
    let est = DeltaEstimator::new(&setup.model, &p, DT, Stencil::default()).unwrap();
    for (e, (oi, o)) in inputs.iter().zip(&outputs).enumerate() {
        let g = est.apply([&o[0], &o[1]], Some([&oi[0], &oi[1]])).unwrap();
        // The same readouts without subtracting the injection: Delta o = A C T o_i.
        let full = est.apply([&o[0], &o[1]], None).unwrap();
        let rms = |v: &[f64]| {
            let m = v.iter().sum::<f64>() / v.len() as f64;
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
        };
        // The injected acceleration of the experiment (its larger channel).
        let sig = rms(&full[0]).max(rms(&full[1]));
        // Highest injected frequency 64 cycles / 1200 s = 53 mHz: (w dt)^2 / 3 = 3.7 %.
        let w = 2.0 * PI * 64.0 / 1200.0 * DT;
        for (ch, gc) in g.iter().enumerate() {
            let res = rms(gc);
            assert!(
                res < w * w / 3.0 * sig,
                "experiment {e}, g{}: residual rms {res:e} vs injected {sig:e}",
                ch + 1
            );
        }
    }
}

/// Welch PSDs (thesis settings, 90 % band) of the acceleration `est` makes of the readouts `o`,
/// and the model's projection for readout noise at `p_noise`.
fn spectra(
    setup: &Setup,
    est: &DeltaEstimator<'_, freefall::model::LpfX, 2>,
    o: &[Vec<f64>],
    p_noise: &[f64],
) -> (AccelPsd, Vec<[f64; 2]>) {
    let g = est.apply([&o[0], &o[1]], None).unwrap();
    let psd = welch_psd(&[&g[0], &g[1]], DT, &WelchConfig::default(), LEVEL).unwrap();
    let model = projection(
        est,
        &setup.model,
        &setup.noise,
        p_noise,
        &psd.f,
        Response::Estimator,
    );
    (psd, model)
}

/// Mean and 90 % band check of a Welch estimate against a model PSD over `[f_lo, f_hi]`.
/// Returns (mean ratio, fraction of bins inside the band, bins).
fn compare(
    f: &[f64],
    est: &[f64],
    model: &[f64],
    lo: f64,
    hi: f64,
    band: (f64, f64),
) -> (f64, f64, usize) {
    let idx: Vec<usize> = (0..f.len())
        .filter(|&k| f[k] >= band.0 && f[k] <= band.1)
        .collect();
    let ratio = idx.iter().map(|&k| est[k] / model[k]).sum::<f64>() / idx.len() as f64;
    let inside = idx
        .iter()
        .filter(|&&k| model[k] >= lo * est[k] && model[k] <= hi * est[k])
        .count() as f64
        / idx.len() as f64;
    (ratio, inside, idx.len())
}

/// Oracle: Welch PSD vs model. The Welch PSD of the acceleration of a simulated noise run agrees
/// with the projection `Delta_h S_o Delta_h^H` of the model (for Delta at the truth and at the
/// guess): the mean ratio per decade is 1 within 5 standard errors of a Welch average, and at
/// least 80 % of the bins hold the model inside their 90 % band. The noise budget sums to the
/// projection (thesis eq. "equation of motion in the sensed coordinates": the sources are
/// uncorrelated, their contributions add) within 1 % (in fact to round-off).
#[test]
fn estimate_psd_matches_the_model_projection_and_the_budget_sums_to_it() {
    let setup = Setup::embedded_continuous(); // the thesis's loop
    let sc = setup.spec.scenario("under_performing").unwrap();
    // Two days: 16 Welch segments of ~34 000 s resolve 0.1 mHz.
    let n = 2 * 86_400;
    let o = noise_run(&setup, &sc.truth, n, 7);
    for p in [&sc.truth, &sc.guess] {
        let est = DeltaEstimator::new(&setup.model, p, DT, Stencil::default()).unwrap();
        let (psd, model) = spectra(&setup, &est, &o, &sc.truth);
        // Welch bins are correlated over ~3 neighbours (92-dB Blackman-Harris ENBW 2 bins plus
        // overlap): the standard error of a mean over m bins is about sqrt(3 * 2 / (nu m)).
        for ch in 0..2 {
            let m: Vec<f64> = model.iter().map(|r| r[ch]).collect();
            for band in [(1e-4, 1e-3), (1e-3, 1e-2), (1e-2, 1e-1), (1e-1, 0.45)] {
                let (ratio, inside, bins) = compare(&psd.f, &psd.psd[ch], &m, psd.lo, psd.hi, band);
                let se = (6.0 / (psd.dof * bins as f64)).sqrt();
                assert!(
                    (ratio - 1.0).abs() < 5.0 * se,
                    "g{} band {band:?}: mean ratio {ratio:.4} (standard error {se:.4}, {bins} bins)",
                    ch + 1
                );
                assert!(
                    inside >= 0.8,
                    "g{} band {band:?}: {inside:.2} inside the band",
                    ch + 1
                );
            }
        }
        let terms = budget(
            &est,
            &setup.model,
            &setup.noise,
            &sc.truth,
            &psd.f,
            Response::Estimator,
        );
        assert_eq!(terms.len(), setup.noise.sources.len());
        assert_budget_sums(&terms, &model, &psd.f, 0.01);
    }
}

/// The budget's terms sum to the projection `model` at every frequency, to `tol` relative.
fn assert_budget_sums(
    terms: &[freefall::accel::BudgetTerm],
    model: &[[f64; 2]],
    f: &[f64],
    tol: f64,
) {
    for (k, row) in model.iter().enumerate() {
        for (ch, want) in row.iter().enumerate() {
            let sum: f64 = terms.iter().map(|t| t.psd[k][ch]).sum();
            assert!(
                (sum / want - 1.0).abs() < tol,
                "f = {}: budget {sum:e} vs projection {want:e}",
                f[k]
            );
        }
    }
}

/// Oracle: the time-domain engine against the frequency-domain model (independent paths). A
/// 2-day noise run of the digital loop at 10 Hz, decimated to 1 Hz by the model's anti-alias
/// FIR, converted by the digital model's Delta (at the truth and at the guess): its Welch S_g12
/// follows the projection with the readout noise folded through the FIR
/// (`projection_of_telemetry`) per band up to the Nyquist frequency within 5 standard errors,
/// and S_g1 up to 0.45 Hz; the budget sums to it. Without the fold the projection misses the
/// FIR's roll-off: measured S_g12 / projection 0.919 over 0.3-0.45 Hz (11 standard errors) and
/// 0.040 over 0.45-0.5 Hz; with it 0.997 and 0.988. Not understood and left out: over
/// 0.45-0.5 Hz the estimate's S_g1 is 11.6 (guess: 13.5) times the folded projection (0.04
/// times the unfolded one), with or without a first difference (so not window leakage); the
/// readouts follow the folded model up to 0.49 Hz, but over 0.49-0.5 Hz (|H|^2 1e-6, only the
/// aliased stopband left) o12 is 3.9 times it (README, "Decimated telemetry").
#[test]
fn time_domain_acceleration_follows_the_projection_through_the_anti_alias_fir() {
    let setup = digital_setup();
    let sc = setup.spec.scenario("under_performing").unwrap();
    let quiet = setup.design("standard").unwrap().noise_only(2.0 * 86_400.0);
    let sim = setup
        .time_domain_simulator(&quiet, &sc.truth, None, None)
        .unwrap();
    let o = sim.noise_run(&mut stream(3, 1));
    let dec = setup.spec.decimator().unwrap();
    for p in [&sc.truth, &sc.guess] {
        let est = DeltaEstimator::new(&setup.model, p, DT, Stencil::default()).unwrap();
        let g = est.apply([&o[0], &o[1]], None).unwrap();
        let psd = welch_psd(&[&g[0], &g[1]], DT, &WelchConfig::default(), LEVEL).unwrap();
        let model = |fold: Option<&freefall::spectral::Decimator>| {
            projection_of_telemetry(
                &est,
                &setup.model,
                &setup.noise,
                &sc.truth,
                &psd.f,
                Response::Estimator,
                fold,
            )
        };
        let (folded, plain) = (model(Some(&dec)), model(None));
        let ratio = |m: &[[f64; 2]], ch: usize, band: (f64, f64)| {
            let idx: Vec<usize> = (0..psd.f.len())
                .filter(|&k| psd.f[k] >= band.0 && psd.f[k] < band.1)
                .collect();
            let r = idx.iter().map(|&k| psd.psd[ch][k] / m[k][ch]).sum::<f64>() / idx.len() as f64;
            (r, (6.0 / (psd.dof * idx.len() as f64)).sqrt())
        };
        let bands = [
            (1e-4, 1e-3),
            (1e-3, 1e-2),
            (1e-2, 0.1),
            (0.1, 0.3),
            (0.3, 0.45),
            (0.45, 0.5),
        ];
        for (ch, top) in [(1, 0.5), (0, 0.45)] {
            for band in bands.iter().filter(|b| b.1 <= top) {
                let (r, se) = ratio(&folded, ch, *band);
                eprintln!(
                    "g{} {band:?}: S / folded projection {r:.4} (standard error {se:.4})",
                    ch + 1
                );
                assert!(
                    (r - 1.0).abs() < 5.0 * se,
                    "g{} {band:?}: S / folded projection {r:.4}, standard error {se:.4}",
                    ch + 1
                );
            }
        }
        let (r, se) = ratio(&plain, 1, (0.3, 0.45));
        assert!(
            (r - 1.0).abs() > 5.0 * se,
            "the unfolded projection should miss the FIR's roll-off: {r:.4}"
        );
        let terms = budget_of_telemetry(
            &est,
            &setup.model,
            &setup.noise,
            &sc.truth,
            &psd.f,
            Response::Estimator,
            Some(&dec),
        );
        assert_budget_sums(&terms, &folded, &psd.f, 1e-9);
    }
}

/// Best-fit parameters of the under-performing scenario quoted by the thesis (sec. 4.6, list
/// "the best-fit values"); the delays, which Delta does not contain, are the truth's.
const THESIS_BEST_FIT: [f64; 7] = [
    -2.9998e-6, -2.0000e-6, -1.4998e-3, 0.61994, 0.599990, 0.6, 0.4,
];

/// Mean of `sqrt(a / b)` over the bins of `f` in `band`.
fn asd_ratio(f: &[f64], a: &[f64], b: &[f64], band: (f64, f64)) -> f64 {
    let idx: Vec<usize> = (0..f.len())
        .filter(|&k| f[k] >= band.0 && f[k] <= band.1)
        .collect();
    idx.iter().map(|&k| (a[k] / b[k]).sqrt()).sum::<f64>() / idx.len() as f64
}

/// Oracle: thesis sec. 4.6, Figure "conv2acc", and the model's projection. Under-performing
/// scenario, 6-day noise run at 1 Hz, Delta at the guess (no identification) vs the truth:
/// - near 50 mHz the estimate exceeds the true-parameter one by a factor in [1.5, 2.5] in
///   amplitude (thesis: about 2, unsuppressed thruster noise);
/// - near 0.4 mHz by the factor the projection `Delta S_o Delta^H` predicts, within 10 %, and at
///   least 2.5. The thesis reports about 4 there; the reference model's suspension controller
///   (designed to reproduce the thesis's closed-loop features, not its industrial law) gives
///   `|Delta22(guess) / Delta22(truth)|` = 2.7 at 0.4 mHz, so the thesis's [3, 5] is not
///   reachable with this model (README, "Total equivalent acceleration");
/// - with the thesis's best-fit parameters the estimate lies inside the 90 % band of the
///   true-parameter estimate at every frequency above 0.1 mHz.
#[test]
fn identification_removes_the_excess_of_the_under_performing_scenario() {
    let setup = Setup::embedded_continuous(); // the thesis's loop
    let sc = setup.spec.scenario("under_performing").unwrap();
    let o = noise_run(&setup, &sc.truth, SIX_DAYS, 11);
    let spectra = |p: &[f64]| {
        let est = DeltaEstimator::new(&setup.model, p, DT, Stencil::default()).unwrap();
        spectra(&setup, &est, &o, &sc.truth)
    };
    let (truth, m_truth) = spectra(&sc.truth);
    let (guess, m_guess) = spectra(&sc.guess);
    let (fit, _) = spectra(&THESIS_BEST_FIT);
    let f = &truth.f;
    let m12 = |m: &[[f64; 2]]| m.iter().map(|r| r[1]).collect::<Vec<f64>>();
    let factor = |band: (f64, f64)| {
        let r = asd_ratio(f, &guess.psd[1], &truth.psd[1], band);
        let r_model = asd_ratio(f, &m12(&m_guess), &m12(&m_truth), band);
        assert!(
            (r / r_model - 1.0).abs() < 0.1,
            "band {band:?} Hz: estimated factor {r:.3} vs model {r_model:.3}"
        );
        r
    };
    let low = factor((0.35e-3, 0.45e-3));
    assert!(low >= 2.5, "0.4 mHz: guess / truth = {low:.2} in amplitude");
    let high = factor((48e-3, 52e-3));
    assert!(
        (1.5..=2.5).contains(&high),
        "50 mHz: guess / truth = {high:.2} in amplitude, expected in [1.5, 2.5]"
    );
    for (k, &fk) in f.iter().enumerate().filter(|(_, &fk)| fk > 1e-4) {
        let (s, t) = (fit.psd[1][k], truth.psd[1][k]);
        assert!(
            s >= truth.lo * t && s <= truth.hi * t,
            "f = {fk:e}: best-fit {s:e} outside [{:e}, {:e}]",
            truth.lo * t,
            truth.hi * t
        );
    }
}

/// `freefall simulate` of the under-performing scenario with a 40000 s noise run at 1 Hz into
/// `dir/ds`; returns its dataset.toml.
fn short_noise_dataset(dir: &std::path::Path) -> std::path::PathBuf {
    let ds = dir.join("ds");
    ok(&[
        "simulate",
        "--scenario",
        "under_performing",
        "--rate",
        "analysis",
        "--noise-duration",
        "40000",
        "--out",
        ds.to_str().unwrap(),
    ]);
    ds.join("dataset.toml")
}

/// Oracle: the documented outputs, and linearity of the budget read back from the files. End to
/// end: `simulate` a short dataset, `accel` its noise run with a segment; accel_psd.parquet holds
/// the whole run and the segment, the budget's sources sum to the projection column, and a
/// reversed segment is a one-line error naming it.
#[test]
fn cli_writes_the_documented_tables() {
    use freefall::accel::job::{DELTA_PARAMETERS_KEY, NOISE_PARAMETERS_KEY};
    use freefall::io::read_parquet;
    let dir = tempfile::tempdir().unwrap();
    let dataset = short_noise_dataset(dir.path());
    let out = dir.path().join("acc");
    let args = |seg: &str| {
        vec![
            "accel".to_string(),
            dataset.to_str().unwrap().to_string(),
            "--scenario".into(),
            "under_performing".into(),
            "--segment".into(),
            seg.into(),
            "--no-plots".into(),
            "--out".into(),
            out.to_str().unwrap().to_string(),
        ]
    };
    let a = args("0:20000");
    ok(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let acc = read_parquet(out.join("accel.parquet")).unwrap();
    assert_eq!(acc.names(), ["t", "g1", "g12"]);
    assert_eq!(acc.num_rows(), 40_000 - 4);
    let psd = read_parquet(out.join("accel_psd.parquet")).unwrap();
    let seg = psd.str_column("segment").unwrap();
    assert!(seg.iter().any(|s| s == "all") && seg.iter().any(|s| s == "0:20000"));
    let model = psd.f64_column("model_g12").unwrap();
    let f = psd.f64_column("f").unwrap();
    let bud = read_parquet(out.join("budget.parquet")).unwrap();
    let (bf, bs) = (
        bud.f64_column("f").unwrap(),
        bud.f64_column("S_g12").unwrap(),
    );
    for (k, fk) in f.iter().enumerate().filter(|(k, _)| seg[*k] == "all") {
        let sum: f64 = (0..bf.len()).filter(|&j| bf[j] == *fk).map(|j| bs[j]).sum();
        assert!(
            (sum / model[k] - 1.0).abs() < 0.01,
            "f = {fk}: {sum:e} vs {:e}",
            model[k]
        );
    }
    // Which parameters made them: --scenario under_performing (the default --use guess) for
    // Delta, and the simulated dataset's [meta.truth] for the readout noise model.
    for (name, t) in [("accel", &acc), ("accel_psd", &psd), ("budget", &bud)] {
        let get = |k: &str| t.meta.get(k).map(String::as_str);
        assert_eq!(
            get(DELTA_PARAMETERS_KEY),
            Some("under_performing guess"),
            "{name}"
        );
        assert_eq!(
            get(NOISE_PARAMETERS_KEY),
            Some("the dataset's [meta.truth]"),
            "{name}"
        );
    }
    // --force: the folder holds the tables above (a non-empty --out is refused first).
    let mut a = args("300:100");
    a.push("--force".into());
    let o = freefall(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("300:100") && err.trim().lines().count() == 1,
        "{err}"
    );
}

/// Oracle: the two analyses' own tables, read back from their files. `accel --compare` of
/// Delta at the guess against Delta at the truth (same run): compare.parquet's ratio is
/// `sqrt(S_g12 / S_g12,ref)` of the two accel_psd.parquet files, compare_budget.parquet's
/// excesses sum to the difference of the two projections (each budget sums to its own), the
/// printed 50 mHz factor is the band mean of that ratio, and spectra on different frequency
/// grids are a one-line error naming the reference folder, with nothing written.
#[test]
fn cli_compares_two_parameter_sets_of_one_run() {
    use freefall::io::read_parquet;
    let dir = tempfile::tempdir().unwrap();
    let dataset = short_noise_dataset(dir.path());
    let (truth, guess) = (dir.path().join("truth"), dir.path().join("guess"));
    // `run` is `ok` where the command must succeed, `freefall` where it must fail.
    let accel = |run: fn(&[&str]) -> Output, set: &str, out: &std::path::Path, extra: &[&str]| {
        let mut a = vec![
            "accel",
            dataset.to_str().unwrap(),
            "--scenario",
            "under_performing",
            "--use",
            set,
            "--no-plots",
            "--out",
            out.to_str().unwrap(),
        ];
        a.extend_from_slice(extra);
        run(&a)
    };
    accel(ok, "truth", &truth, &[]);
    // A reference on another frequency grid: refused before anything is written.
    let bad = dir.path().join("bad");
    let o = accel(
        freefall,
        "guess",
        &bad,
        &[
            "--compare",
            truth.to_str().unwrap(),
            "--welch-segments",
            "8",
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success()
            && err.contains(truth.to_str().unwrap())
            && err.contains("--welch-segments")
            && err.trim().lines().count() == 1,
        "{err}"
    );
    assert!(!bad.join("compare.parquet").exists());
    let o = accel(ok, "guess", &guess, &["--compare", truth.to_str().unwrap()]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    let whole = |d: &std::path::Path, col: &str| {
        let t = read_parquet(d.join("accel_psd.parquet")).unwrap();
        let seg = t.str_column("segment").unwrap().to_vec();
        let c = t.f64_column(col).unwrap();
        (0..c.len())
            .filter(|&k| seg[k] == "all")
            .map(|k| c[k])
            .collect::<Vec<f64>>()
    };
    let (f, s_t, s_g) = (
        whole(&truth, "f"),
        whole(&truth, "S_g12"),
        whole(&guess, "S_g12"),
    );
    let (m_t, m_g) = (whole(&truth, "model_g12"), whole(&guess, "model_g12"));
    let cmp = read_parquet(guess.join("compare.parquet")).unwrap();
    let ratio = cmp.f64_column("ratio_g12").unwrap();
    assert_eq!(cmp.f64_column("f").unwrap(), f.as_slice());
    for k in 0..f.len() {
        let want = (s_g[k] / s_t[k]).sqrt();
        assert!((ratio[k] / want - 1.0).abs() < 1e-12, "f = {}", f[k]);
    }
    let bud = read_parquet(guess.join("compare_budget.parquet")).unwrap();
    let (bf, bx) = (
        bud.f64_column("f").unwrap(),
        bud.f64_column("excess_S_g12").unwrap(),
    );
    for k in (0..f.len()).step_by(97) {
        let sum: f64 = (0..bf.len())
            .filter(|&j| bf[j] == f[k])
            .map(|j| bx[j])
            .sum();
        let want = m_g[k] - m_t[k];
        assert!(
            (sum - want).abs() <= 0.02 * m_g[k].max(m_t[k]),
            "f = {}: excess {sum:e} vs projections' difference {want:e}",
            f[k]
        );
    }
    let band: Vec<usize> = (0..f.len())
        .filter(|&k| f[k] >= 48e-3 && f[k] <= 52e-3)
        .collect();
    let factor = band.iter().map(|&k| ratio[k]).sum::<f64>() / band.len() as f64;
    let line = stdout
        .lines()
        .find(|l| l.starts_with("48-52 mHz"))
        .unwrap_or_else(|| panic!("no 50 mHz line in:\n{stdout}"));
    assert!(
        line.contains(&format!("reference = {factor:.2} ")) && line.contains("thruster"),
        "{line} (band mean {factor:.3})"
    );
}

/// Oracle: each piece converted alone, and the model's projection. Telemetry has gaps: a
/// 40000 s noise run with 600 samples removed at 15000 s converts piece by piece. The first
/// piece's acceleration equals `accel` of that piece written as its own file, bit for bit; the
/// table keeps both pieces with the gap in `t`; the note names the pieces and the Welch
/// segments each adds (9 + 16); and the averaged S_g12 follows the projection within 10 % over
/// 2-20 mHz (72 bins of 25 segments, standard error about 3.5 %; measured 0.985).
#[test]
fn cli_converts_a_run_with_gaps_piece_by_piece() {
    use freefall::io::{read_parquet, read_run, write_parquet, write_run, Run, Table};
    let dir = tempfile::tempdir().unwrap();
    let dataset = short_noise_dataset(dir.path());
    let run = read_run(dataset.with_file_name("noise.parquet")).unwrap();
    let (cut, resume) = (15_000, 15_600);
    let keep: Vec<usize> = (0..cut).chain(resume..run.len()).collect();
    let t = run.time();
    let mut table = Table::new()
        .with_f64("t", keep.iter().map(|&k| t[k]).collect())
        .unwrap();
    for (name, col) in &run.columns {
        table = table
            .with_f64(name.clone(), keep.iter().map(|&k| col[k]).collect())
            .unwrap();
    }
    let gapped = dir.path().join("gapped.parquet");
    write_parquet(&gapped, &table).unwrap();
    let first = Run::new(
        run.t0,
        run.dt,
        run.columns
            .iter()
            .map(|(n, c)| (n.clone(), c[..cut].to_vec()))
            .collect(),
    )
    .unwrap();
    let alone = dir.path().join("first.parquet");
    write_run(&alone, &first).unwrap();
    let accel = |input: &std::path::Path, out: &str| {
        let out = dir.path().join(out);
        let o = ok(&[
            "accel",
            input.to_str().unwrap(),
            "--scenario",
            "under_performing",
            "--use",
            "truth",
            "--no-plots",
            "--out",
            out.to_str().unwrap(),
        ]);
        (out, String::from_utf8_lossy(&o.stderr).to_string())
    };
    let (out, stderr) = accel(&gapped, "gapped");
    assert!(
        stderr.contains("2 contiguous pieces")
            && stderr.contains(": 9;")
            && stderr.contains(": 16)"),
        "{stderr}"
    );
    let (out_alone, _) = accel(&alone, "alone");
    let g = read_parquet(out.join("accel.parquet")).unwrap();
    let g_alone = read_parquet(out_alone.join("accel.parquet")).unwrap();
    let tg = g.f64_column("t").unwrap();
    assert_eq!(tg.len(), (cut - 4) + (run.len() - resume - 4));
    let jumps: Vec<f64> = tg
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|d| *d > 1.5)
        .collect();
    // From the first piece's last kept sample, t = cut - 1 - 2, to the second's first, resume + 2.
    assert_eq!(jumps, [(resume + 2 - (cut - 3)) as f64]);
    for ch in ["t", "g1", "g12"] {
        let (a, b) = (g.f64_column(ch).unwrap(), g_alone.f64_column(ch).unwrap());
        assert_eq!(
            &a[..b.len()],
            b,
            "{ch}: the first piece differs from its own conversion"
        );
    }
    let psd = read_parquet(out.join("accel_psd.parquet")).unwrap();
    let (f, s, m) = (
        psd.f64_column("f").unwrap(),
        psd.f64_column("S_g12").unwrap(),
        psd.f64_column("model_g12").unwrap(),
    );
    let ratios: Vec<f64> = (0..f.len())
        .filter(|&k| (2e-3..=20e-3).contains(&f[k]))
        .map(|k| s[k] / m[k])
        .collect();
    let mean = ratios.iter().sum::<f64>() / ratios.len() as f64;
    eprintln!(
        "S_g12 / projection over 2-20 mHz: {mean:.4} ({} bins)",
        ratios.len()
    );
    assert!(
        (mean - 1.0).abs() < 0.1,
        "S_g12 / projection over 2-20 mHz: {mean:.3} ({} bins)",
        ratios.len()
    );
}

/// Mean of `psd[k]` over the bins of `f` in `band`.
fn band_mean(f: &[f64], psd: &[f64], band: (f64, f64)) -> f64 {
    let v: Vec<f64> = (0..f.len())
        .filter(|&k| f[k] >= band.0 && f[k] <= band.1)
        .map(|k| psd[k])
        .collect();
    v.iter().sum::<f64>() / v.len() as f64
}

/// Oracle: thesis Figures "transients_acc" and "transients_psd", and the loop's own equation of
/// motion. A run of the digital loop (time-domain engine, an independent path from the
/// frequency-domain templates) started from the thesis's initial conditions carries the loop's
/// free response. Delta with the right parameters maps that response to (nearly) zero; with the
/// under-performing guess it does not. S_g12 averaged over 0.7-1.5 mHz in the first 4000 s
/// against a steady stretch (20000 s to the end), for Delta of the thesis's continuous loop and
/// of the sampled-data model of the loop that made the data:
/// - noise-free, the free response through Delta at the truth leaves 6.8e-4 (continuous) and
///   5.3e-5 (digital) of the noise's steady level; asserted below 1e-2. Before the estimator
///   fitted the controllers' initial state (`accel::operator`: the suspension law's memory of
///   the 28 s the loop runs before the first telemetry sample) the continuous Delta left 2.59;
///   before the padding blended the series' ends, the digital Delta left 28;
/// - with noise, seeds 1-5: continuous 2.25, 0.29, 0.38, 0.26, 0.82, digital 2.30, 0.30, 0.38,
///   0.25, 0.83 with the thesis's best fit (the noise alone, free response subtracted, gives
///   2.30, 0.29, 0.39, 0.25, 0.83: seed 1's excess is its noise), 16 400-35 700 with the guess.
///   Asserted: the guess above 1000x on every seed, the best fit below 2.5x on every seed and
///   below 1.5x on average.
#[test]
fn calibrated_delta_suppresses_the_start_up_transient() {
    for setup in [Setup::embedded_continuous(), digital_setup()] {
        suppresses_the_start_up_transient(&setup);
    }
}

/// The run and Delta both come from `setup` (the time-domain engine runs the digital loop
/// either way; `setup` chooses the model whose Delta is applied).
fn suppresses_the_start_up_transient(setup: &Setup) {
    use freefall::sim::time_domain::InitialConditions;
    let name = setup.spec.control_loop.kind;
    let sc = setup.spec.scenario("under_performing").unwrap();
    let design = setup.design("standard").unwrap();
    let quiet = design.noise_only(40_000.0);
    let initial: InitialConditions = "o1=2.4e-7,o12=3.6e-7,v1=-5e-10,v12=-4e-12".parse().unwrap();
    let sim = setup
        .time_domain_simulator(&quiet, &sc.truth, None, Some(&initial))
        .unwrap();
    let welch = WelchConfig {
        segments: 2,
        ..WelchConfig::default()
    };
    let band = (0.7e-3, 1.5e-3);
    let estimate = |o: &[Vec<f64>], p: &[f64]| {
        let est = DeltaEstimator::new(&setup.model, p, DT, Stencil::default()).unwrap();
        est.apply([&o[0], &o[1]], None).unwrap()
    };
    let level = |g: &[Vec<f64>], a: usize, b: usize| {
        let b = b.min(g[1].len());
        let psd = welch_psd(&[&g[0][a..b], &g[1][a..b]], DT, &welch, LEVEL).unwrap();
        band_mean(&psd.f, &psd.psd[1], band)
    };
    let ratio = |o: &[Vec<f64>], p: &[f64]| {
        let g = estimate(o, p);
        level(&g, 0, 4000) / level(&g, 20_000, usize::MAX)
    };
    // Noise-free: the free response alone, at the truth, against the noise's steady level.
    let steady = level(
        &estimate(&sim.noise_run(&mut stream(1, 1)), &sc.truth),
        20_000,
        usize::MAX,
    );
    let free = level(
        &estimate(&sim.noise_free().outputs.remove(0), &sc.truth),
        0,
        4000,
    );
    eprintln!(
        "{name:?} Delta: free response through Delta(truth), first 4000 s / steady noise: {:.2e}",
        free / steady
    );
    assert!(
        free < 1e-2 * steady,
        "{name:?}: free response left by Delta(truth): {:.3e} of the steady level",
        free / steady
    );
    let seeds = 1..6u64;
    let mut fit_mean = 0.0;
    for seed in seeds.clone() {
        let o = sim.noise_run(&mut stream(seed, 1));
        let (fit, guess) = (ratio(&o, &THESIS_BEST_FIT), ratio(&o, &sc.guess));
        eprintln!(
            "{name:?} Delta, seed {seed}: S_g12 transient / steady: best fit {fit:.2}, guess {guess:.0}"
        );
        assert!(
            guess > 1000.0,
            "{name:?}, seed {seed}: the guess suppresses the transient: {guess:.1}"
        );
        assert!(
            fit < 2.5,
            "{name:?}, seed {seed}: best-fit Delta leaves the transient: {fit:.2}"
        );
        fit_mean += fit / seeds.clone().count() as f64;
    }
    assert!(
        fit_mean < 1.5,
        "{name:?}: best-fit Delta leaves the transient: mean {fit_mean:.2}"
    );
}

/// Oracle: the loop's own equation of motion. Without noise, a run of the digital loop (time-
/// domain engine) from the thesis's initial conditions is the free response, which Delta of the
/// sampled-data model at the true parameters maps to zero acceleration, up to the estimator's
/// discretisation and the series' first samples. Before the held plant's half-step advance was
/// applied as a stencil (`ClosedLoopModel::inertia_advance`), its FFT multiplier's jump at
/// Nyquist left an alternating tail: g12 rms 4.2e-11 m s^-2 over 1000-4000 s, 16 times the
/// rms of the noise-only estimate (2.6e-12, broadband readout noise through s^2); after it,
/// 5.6e-16; since the padding blends the series' ends instead of jumping to zero and the
/// suspension mode is fitted under the alternating terms, 8.4e-19 (guess: 2.9e-13), printed by
/// this test.
#[test]
fn digital_delta_cancels_the_free_response_of_the_digital_loop() {
    use freefall::sim::time_domain::InitialConditions;
    let setup = digital_setup();
    let sc = setup.spec.scenario("under_performing").unwrap();
    let quiet = setup.design("standard").unwrap().noise_only(8_000.0);
    let initial: InitialConditions = "o1=2.4e-7,o12=3.6e-7,v1=-5e-10,v12=-4e-12".parse().unwrap();
    let sim = setup
        .time_domain_simulator(&quiet, &sc.truth, None, Some(&initial))
        .unwrap();
    let o = sim.noise_free().outputs.remove(0);
    let rms = |p: &[f64]| {
        let est = DeltaEstimator::new(&setup.model, p, DT, Stencil::default()).unwrap();
        let g = est.apply([&o[0], &o[1]], None).unwrap();
        let x = &g[1][1000..4000];
        (x.iter().map(|v| v * v).sum::<f64>() / x.len() as f64).sqrt()
    };
    let (truth, guess) = (rms(&sc.truth), rms(&sc.guess));
    eprintln!("free response through Delta, g12 rms over 1000-4000 s: truth {truth:.3e}, guess {guess:.3e}");
    // Four decades below the noise-only g12 rms (2.6e-12 m s^-2 at 1 Hz).
    assert!(truth < 1e-16, "truth: {truth:e}");
    assert!(guess > 100.0 * truth, "guess {guess:e} vs truth {truth:e}");
}
