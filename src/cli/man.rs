//! `freefall man`: the manual pages. Without `--out` the top page goes to stdout; with
//! `--out DIR`, `freefall.1` and one `freefall-<subcommand>.1` per subcommand (nested ones too:
//! `freefall-campaign-run.1`) are written there, each written atomically. Every page ends with
//! EXAMPLES (command lines of README.md's tour and docs/user-guide.md) and ENVIRONMENT.

use std::path::{Path, PathBuf};

use anyhow::Result;

/// `freefall man [--out DIR]`.
#[derive(Debug, clap::Args)]
pub struct ManArgs {
    /// Write every page (freefall.1, freefall-<subcommand>.1, nested ones too) into this folder
    /// instead of printing the top page.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Example command lines of each page, keyed by the page's name (`freefall-campaign-run`): each
/// a (what it does, command line) pair.
fn examples(page: &str) -> &'static [(&'static str, &'static str)] {
    match page {
        "freefall" => &[
            ("Simulate a dataset (experiments plus a noise-only run)", "freefall simulate --loop continuous --out ds --seed 7"),
            ("Fit the model to it", "freefall fit --loop continuous ds/dataset.toml --out fit"),
            ("Run a Monte Carlo campaign", "freefall campaign run campaigns/monte_carlo.toml --out out/mc --threads 2"),
            ("Write all manual pages", "freefall man --out man"),
        ],
        "freefall-model" => &[
            ("Transfer functions on the default grid", "freefall model transfer --loop continuous --out tf.parquet"),
            ("Fisher errors of the standard design", "freefall model fisher --loop continuous --scenario monte_carlo --design standard --out fisher.parquet"),
        ],
        "freefall-model-transfer" => &[
            ("T_{oi->o} from 1e-4 to 0.1 Hz at 200 points", "freefall model transfer --loop continuous --fmin 1e-4 --fmax 0.1 --points 200 --out tf.parquet"),
            ("The 7x7 transfer functions of the xy model", "freefall model transfer --model lpf_xy --out tf_xy.parquet"),
        ],
        "freefall-model-noise" => &[
            ("Readout cross-PSD of the nominal model", "freefall model noise --loop continuous --out noise.parquet"),
            ("Under a scenario's true parameters", "freefall model noise --loop continuous --scenario monte_carlo --out noise.parquet"),
        ],
        "freefall-model-fisher" => &[
            ("Fisher errors (and fisher_corr.parquet)", "freefall model fisher --loop continuous --scenario monte_carlo --design standard --out fisher.parquet"),
            ("The xy model's standard design", "freefall model fisher --model lpf_xy --design standard_xy --out fisher_xy.parquet"),
        ],
        "freefall-simulate" => &[
            ("A dataset in the measured-data format", "freefall simulate --loop continuous --out ds --seed 7"),
            ("With an effect the model lacks", "freefall simulate --loop continuous --effect loss_angle_tm2=0.01 --seed 3 --noise-duration 10800 --out lossy"),
            ("Time-domain engine (digital loop)", "freefall simulate --engine time-domain --seed 5 --out td"),
        ],
        "freefall-psd" => &[
            ("Welch cross-spectra of the noise run", "freefall psd ds/noise.parquet --out noise_psd.parquet"),
        ],
        "freefall-whiten" => &[
            ("Whiten a run with the filter fitted on the noise run", "freefall whiten ds/noise.parquet --noise ds/noise.parquet --out white.parquet"),
            ("Whiten with the model noise PSD", "freefall whiten ds/noise.parquet --model-psd --loop continuous --out white.parquet"),
        ],
        "freefall-fit" => &[
            ("Fit a dataset", "freefall fit --loop continuous ds/dataset.toml --out fit"),
            ("Start from a scenario's guess", "freefall fit --loop continuous up6/dataset.toml --guess under_performing --out fit"),
        ],
        "freefall-campaign" => &[
            ("Run a campaign on two threads", "freefall campaign run campaigns/monte_carlo.toml --out out/mc --threads 2"),
            ("Merge shards", "freefall campaign merge out/p1 out/p2 --out out/mc"),
        ],
        "freefall-campaign-run" => &[
            ("Run a campaign on two threads", "freefall campaign run campaigns/monte_carlo.toml --out out/mc --threads 2"),
            ("Shard 1 of 2 (continue it later with --resume)", "freefall campaign run campaigns/monte_carlo.toml --shard 1/2 --out out/p1"),
        ],
        "freefall-campaign-merge" => &[
            ("Merge the two shards into one run", "freefall campaign merge out/p1 out/p2 --out out/mc"),
        ],
        "freefall-campaign-slurm" => &[
            ("A SLURM job array of 8 shards and its merge job", "freefall campaign slurm campaigns/monte_carlo.toml --shards 8 --out out/slurm --time 01:00:00"),
        ],
        "freefall-design" => &[
            ("Optimise the injections for every criterion", "freefall design optimize --loop continuous --criterion all --out out/design"),
            ("Score a design", "freefall design evaluate --loop continuous out/design/designs/d-information_separate.toml"),
        ],
        "freefall-design-optimize" => &[
            ("Optimise the injections for every criterion", "freefall design optimize --loop continuous --criterion all --out out/design"),
        ],
        "freefall-design-evaluate" => &[
            ("Score a design written by design optimize", "freefall design evaluate --loop continuous out/design/designs/d-information_separate.toml"),
        ],
        "freefall-design-validate" => &[
            ("The thesis's validation campaign", "freefall design validate campaigns/optimal_design.toml --out out/validate"),
        ],
        "freefall-diagnose" => &[
            ("Find the effect a dataset holds", "freefall diagnose --loop continuous lossy/dataset.toml --out lossy-diagnosis"),
            ("List the effects it tests", "freefall diagnose --list-effects"),
        ],
        "freefall-completions" => &[
            ("Bash completions, to source from ~/.bashrc", "freefall completions bash > ~/.freefall.bash"),
            ("Zsh completions", "freefall completions zsh > _freefall"),
        ],
        "freefall-man" => &[
            ("Read the top page", "freefall man | man -l -"),
            ("Write every page", "freefall man --out man"),
        ],
        "freefall-accel" => &[
            ("Acceleration of a run under the true parameters", "freefall accel --loop continuous ds/dataset.toml --scenario monte_carlo --use truth --segment 0:3000 --segment 6000:9000 --out ds-accel"),
            ("Under a fit's estimates", "freefall accel --loop continuous up6/dataset.toml --params fit/estimates.parquet --compare acc_truth --out acc_fit"),
        ],
        _ => &[],
    }
}

/// The environment variables freefall reads: (name, what it does).
pub const ENVIRONMENT: &[(&str, &str)] = &[
    (
        "FREEFALL_MEMORY_BUDGET",
        "Memory budget in bytes against which the sizes of large allocations (the whitening filter's normal matrix, simulated runs) are checked before they are made; default half the machine's available memory.",
    ),
    (
        "FREEFALL_PLOT_SCRIPT",
        "A Python script run with python3 on the output folder instead of the embedded plot script (diagnose, accel).",
    ),
    (
        "RAYON_NUM_THREADS",
        "Number of worker threads of the parallel parts (default: the number of cores); campaign run --threads overrides it.",
    ),
];

/// Renders the page of `cmd` (a built command: its display name is the page name) with the
/// EXAMPLES and ENVIRONMENT sections appended.
fn render(cmd: &clap::Command, parent: Option<&clap::Command>) -> Result<Vec<u8>> {
    let man = clap_mangen::Man::new(cmd.clone());
    let mut out = Vec::new();
    man.render(&mut out)?;
    let page = cmd.get_display_name().unwrap_or(cmd.get_name());
    let mut lines: Vec<(String, String)> = examples(page)
        .iter()
        .map(|(w, l)| (w.to_string(), l.to_string()))
        .collect();
    if let (true, Some(parent)) = (cmd.get_name() == "help", parent) {
        // clap's `help` subcommand: the help of the parent's first other subcommand.
        let path = page.trim_end_matches("-help").replace('-', " ");
        if let Some(sub) = parent.get_subcommands().find(|s| s.get_name() != "help") {
            lines.push((
                format!("The help of {path} {}", sub.get_name()),
                format!("{path} help {}", sub.get_name()),
            ));
        }
    }
    out.extend_from_slice(b".SH EXAMPLES\n");
    for (what, line) in &lines {
        let (what, line) = (roff_text(what), roff_text(line));
        out.extend_from_slice(format!(".PP\n{what}\n.PP\n.RS 4\n\\fB{line}\\fR\n.RE\n").as_bytes());
    }
    out.extend_from_slice(b".SH ENVIRONMENT\n");
    for (name, what) in ENVIRONMENT {
        out.extend_from_slice(format!(".TP\n\\fB{name}\\fR\n{}\n", roff_text(what)).as_bytes());
    }
    Ok(out)
}

/// `s` as roff text: backslashes escaped, hyphens as minus signs (so that copied options work),
/// a leading `.` or `'` (a control line) guarded.
fn roff_text(s: &str) -> String {
    let t = s.replace('\\', "\\e").replace('-', "\\-");
    if t.starts_with('.') || t.starts_with('\'') {
        format!("\\&{t}")
    } else {
        t
    }
}

/// The built command and its subcommands, depth first (hidden ones left out; clap's own `help`
/// subcommands kept as one page each, since the parent pages list them, but not the copy of
/// the command tree under them), each with its parent.
fn pages(mut cmd: clap::Command) -> Vec<(clap::Command, Option<clap::Command>)> {
    cmd.build();
    fn walk(
        cmd: &clap::Command,
        parent: Option<&clap::Command>,
        acc: &mut Vec<(clap::Command, Option<clap::Command>)>,
    ) {
        acc.push((cmd.clone(), parent.cloned()));
        if parent.is_some() && cmd.get_name() == "help" {
            return; // one page for `help`, not one per copy of the tree under it
        }
        for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set()) {
            walk(sub, Some(cmd), acc);
        }
    }
    let mut acc = Vec::new();
    walk(&cmd, None, &mut acc);
    acc
}

/// Prints the top page, or with `out` writes every page into that folder (created if missing).
pub fn run(command: clap::Command, out: Option<&Path>) -> Result<()> {
    let pages = pages(command);
    let Some(dir) = out else {
        let top = render(&pages[0].0, None)?;
        out!("{}", String::from_utf8_lossy(&top));
        return Ok(());
    };
    crate::io::ensure_dir(dir)?;
    for (cmd, parent) in &pages {
        let name = format!("{}.1", cmd.get_display_name().unwrap_or(cmd.get_name()));
        let path = dir.join(&name);
        crate::io::write_bytes_atomic(&path, &render(cmd, parent.as_ref())?)?;
        info!("wrote {}", path.display());
    }
    Ok(())
}
