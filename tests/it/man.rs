//! `freefall man --out DIR`: one roff page per command, nested subcommands included, each with
//! EXAMPLES and ENVIRONMENT; plain `freefall man` still prints the top page.

use crate::common;

use std::collections::BTreeSet;

/// The `.SH` section names of a roff page.
fn sections(page: &str) -> Vec<String> {
    page.lines()
        .filter_map(|l| l.strip_prefix(".SH "))
        .map(|s| s.trim_matches('"').to_string())
        .collect()
}

/// The pages a page lists in its SUBCOMMANDS section (`freefall\-model(1)` -> `freefall-model`).
fn listed_pages(page: &str) -> BTreeSet<String> {
    let text = page.replace("\\-", "-");
    let mut out = BTreeSet::new();
    for (i, _) in text.match_indices("(1)") {
        let start = text[..i]
            .rfind(|c: char| !(c.is_ascii_alphanumeric() || c == '-' || c == '_'))
            .map_or(0, |j| j + 1);
        let name = &text[start..i];
        if name.starts_with("freefall") {
            out.insert(name.to_string());
        }
    }
    out
}

#[test]
fn man_out_writes_every_page_with_examples_and_environment() {
    // Oracle: the command tree `freefall --help` and `freefall <cmd> --help` list (clap's own
    // help), the roff title macro `.TH NAME 1`, and the names every top page links to.
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("man");
    common::ok(&["man", "--out", dir.to_str().unwrap()]);
    let mut expected = vec!["freefall".to_string()];
    for cmd in [
        "model", "simulate", "psd", "whiten", "fit", "campaign", "design", "diagnose",
    ] {
        expected.push(format!("freefall-{cmd}"));
    }
    for (cmd, subs) in [
        ("model", &["transfer", "noise", "fisher"][..]),
        ("campaign", &["run", "merge", "slurm"][..]),
        ("design", &["optimize", "evaluate", "validate"][..]),
    ] {
        let help = String::from_utf8_lossy(&common::ok(&[cmd, "--help"]).stdout).to_string();
        for sub in subs {
            assert!(
                help.contains(&format!("  {sub} ")),
                "{cmd} --help lists {sub}"
            );
            expected.push(format!("freefall-{cmd}-{sub}"));
        }
    }
    expected.extend(["freefall-completions", "freefall-man", "freefall-accel"].map(String::from));
    let written: BTreeSet<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    for name in &expected {
        let file = format!("{name}.1");
        assert!(written.contains(&file), "{file} missing from {written:?}");
        let page = std::fs::read_to_string(dir.join(&file)).unwrap();
        let title = page
            .lines()
            .find(|l| l.starts_with(".TH "))
            .unwrap_or_else(|| panic!("{file}: no .TH line"));
        assert!(
            title.starts_with(&format!(".TH {name} 1")),
            "{file}: {title}"
        );
        let secs = sections(&page);
        for sec in ["NAME", "SYNOPSIS", "EXAMPLES", "ENVIRONMENT"] {
            assert!(secs.iter().any(|s| s == sec), "{file}: sections {secs:?}");
        }
        // Every example runs the page's own command: `freefall-campaign-run` -> `freefall campaign run`.
        let command = name.replace('-', " ");
        let examples = page.split(".SH EXAMPLES").nth(1).unwrap();
        let examples = examples.split(".SH ").next().unwrap().replace("\\-", "-");
        assert!(
            examples.contains(&format!("\\fB{command}")),
            "{file}: no example of `{command}` in {examples}"
        );
        for var in [
            "FREEFALL_MEMORY_BUDGET",
            "FREEFALL_PLOT_SCRIPT",
            "RAYON_NUM_THREADS",
        ] {
            assert!(page.contains(var), "{file}: ENVIRONMENT lacks {var}");
        }
        for listed in listed_pages(&page) {
            assert!(
                written.contains(&format!("{listed}.1")),
                "{file} lists {listed}(1), which was not written"
            );
        }
    }
    // clap's `help` subcommand gets one page per level, not a copy of the whole tree.
    let under_help: Vec<_> = written.iter().filter(|f| f.contains("-help-")).collect();
    assert!(under_help.is_empty(), "pages under help: {under_help:?}");
    let top = std::fs::read_to_string(dir.join("freefall.1")).unwrap();
    assert!(listed_pages(&top).contains("freefall-accel"), "{top}");
    // Plain `freefall man` prints the same top page.
    let printed = common::ok(&["man"]);
    assert_eq!(String::from_utf8_lossy(&printed.stdout), top);
}

#[test]
fn environment_section_names_every_variable_the_source_reads() {
    // Oracle: the source itself: every `FREEFALL_*` name in src/ (the variables freefall reads)
    // is in the ENVIRONMENT section.
    let mut names = BTreeSet::new();
    let mut stack = vec![std::path::PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/src"
    ))];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let text = std::fs::read_to_string(&p).unwrap();
                for (i, _) in text.match_indices("FREEFALL_") {
                    let name: String = text[i..]
                        .chars()
                        .take_while(|c| c.is_ascii_uppercase() || *c == '_' || c.is_ascii_digit())
                        .collect();
                    names.insert(name);
                }
            }
        }
    }
    assert!(names.contains("FREEFALL_MEMORY_BUDGET"), "{names:?}");
    let page = String::from_utf8_lossy(&common::ok(&["man"]).stdout).to_string();
    let env = page
        .split(".SH ENVIRONMENT")
        .nth(1)
        .expect("ENVIRONMENT section");
    for name in &names {
        assert!(env.contains(name.as_str()), "ENVIRONMENT lacks {name}");
    }
}
