//! `freefall man`: the manual pages. Without `--out` the top page goes to stdout; with
//! `--out DIR`, `freefall.1` and one `freefall-<subcommand>.1` per subcommand (nested ones too:
//! `freefall-campaign-run.1`) are written there, each written atomically. Every page ends with
//! EXAMPLES (command lines of README.md's tour and docs/user-guide.md) and ENVIRONMENT.

use std::path::Path;

use anyhow::Result;

/// The examples of every page (a data file; its format is in its header).
const EXAMPLES: &str = include_str!("man_examples.txt");

/// The examples of the page named `page` (`freefall-campaign-run`): (what it does, command line).
fn examples(page: &str) -> Vec<(String, String)> {
    let (mut here, mut what, mut acc) = (false, "", Vec::new());
    for line in EXAMPLES.lines().filter(|l| !l.starts_with('#')) {
        if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            here = name == page;
        } else if let (true, Some(cmd)) = (here, line.trim_start().strip_prefix("$ ")) {
            acc.push((std::mem::take(&mut what).to_string(), cmd.to_string()));
        } else if here && !line.trim().is_empty() {
            what = line;
        }
    }
    acc
}

/// Renders the page of `cmd` (a built command: its display name is the page name) with the
/// EXAMPLES and ENVIRONMENT sections appended.
fn render(cmd: &clap::Command) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    clap_mangen::Man::new(cmd.clone()).render(&mut out)?;
    let page = cmd.get_display_name().unwrap_or(cmd.get_name());
    out.extend_from_slice(b".SH EXAMPLES\n");
    for (what, line) in &examples(page) {
        let (what, line) = (roff_text(what), roff_text(line));
        out.extend_from_slice(format!(".PP\n{what}\n.PP\n.RS 4\n\\fB{line}\\fR\n.RE\n").as_bytes());
    }
    out.extend_from_slice(b".SH ENVIRONMENT\n");
    for (name, what) in crate::io::console::ENVIRONMENT {
        out.extend_from_slice(format!(".TP\n\\fB{name}\\fR\n{}\n", roff_text(what)).as_bytes());
    }
    Ok(out)
}

/// `s` as roff text: backslashes escaped, hyphens as minus signs (so that copied options work),
/// a leading `.` or `'` (a control line) guarded.
fn roff_text(s: &str) -> String {
    let t = s.replace('\\', "\\e").replace('-', "\\-");
    if t.starts_with(['.', '\'']) {
        format!("\\&{t}")
    } else {
        t
    }
}

/// Writes the pages of `cmd` and its subcommands, depth first, into `dir` (hidden ones left
/// out; clap's own `help` subcommands kept as one page each, since the parent pages list them,
/// but not the copy of the command tree under them).
fn write_pages(cmd: &clap::Command, dir: &Path) -> Result<()> {
    let path = dir.join(format!(
        "{}.1",
        cmd.get_display_name().unwrap_or(cmd.get_name())
    ));
    crate::io::write_bytes_atomic(&path, &render(cmd)?)?;
    info!("wrote {}", path.display());
    if cmd.get_name() != "help" {
        for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set()) {
            write_pages(sub, dir)?;
        }
    }
    Ok(())
}

/// Prints the top page, or with `out` writes every page into that folder (created if missing).
pub fn run(mut command: clap::Command, out: Option<&Path>) -> Result<()> {
    command.build();
    let Some(dir) = out else {
        out!("{}", String::from_utf8_lossy(&render(&command)?));
        return Ok(());
    };
    crate::io::ensure_dir(dir)?;
    write_pages(&command, dir)
}
