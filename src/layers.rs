//! The layer order of the top-level modules, and the test that keeps it: every `crate::` path
//! of a module's code outside its unit tests names a module at its own level or below, and no
//! two modules import each other, directly or through others.
//!
//! Lower first. A module may import the modules of earlier levels and those of its own level,
//! as long as that makes no cycle:
//!
//! - `numerics`: what has no physics in it;
//! - `data`, `config`: the shared data types and the range checks of settings;
//! - `spectral`: windows, Welch estimates, the anti-alias decimator (the model file's
//!   decimator is one);
//! - `model`: operators, closed-loop algebra, the model file schema;
//! - `signal`, `noise`, `io`: injection designs, noise sources and generation, files;
//! - `forward`: templates and Fisher information;
//! - `fit`: whitening, likelihood, estimators;
//! - `setup`: a model file assembled into model, noise model, designs and whitening filters;
//! - `sim`: the simulators (built from a setup), effect injection, the `simulate` job;
//! - `units`, `analysis`, `accel`, `posterior`, `campaign`, `design`, `diagnose`: the jobs, each using the
//!   ones before it;
//! - `cli`: the command line.
//!
//! Only `crate::` paths count (`use crate::{a, b}` groups too, and `super::` chains that climb
//! out of a top-level module); comments, strings and `#[cfg(test)]` items are skipped.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The documented order, lower first (docs/architecture.md, "Layers").
const LAYERS: &[&[&str]] = &[
    &["numerics"],
    &["data", "config"],
    &["spectral"],
    &["model"],
    &["signal", "noise", "io"],
    &["forward"],
    &["fit"],
    &["setup"],
    &["sim"],
    &["units"],
    &["analysis"],
    &["accel"],
    &["posterior"],
    &["campaign"],
    &["design"],
    &["diagnose"],
    &["cli"],
];

/// One `crate::` reference: which file, which top-level module it is in, which it names, and
/// the line it is on.
#[derive(Debug, Clone)]
struct Import {
    file: String,
    line: usize,
    from: String,
    to: String,
    text: String,
}

fn level(module: &str) -> Option<usize> {
    LAYERS.iter().position(|l| l.contains(&module))
}

/// `text` with comments removed and the contents of string and char literals blanked (newlines
/// kept, so line numbers hold).
fn code_only(text: &str) -> String {
    let c: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    let blank = |ch: char| if ch == '\n' { '\n' } else { ' ' };
    while i < c.len() {
        let next = c.get(i + 1).copied();
        if c[i] == '/' && next == Some('/') {
            while i < c.len() && c[i] != '\n' {
                i += 1;
            }
        } else if c[i] == '/' && next == Some('*') {
            let mut depth = 0;
            while i < c.len() {
                if c[i] == '/' && c.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if c[i] == '*' && c.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    out.push(blank(c[i]));
                    i += 1;
                }
            }
        } else if c[i] == 'r'
            && (next == Some('"') || next == Some('#'))
            && (i == 0 || !(c[i - 1].is_alphanumeric() || c[i - 1] == '_'))
        {
            // Raw string r"..." or r#"..."#.
            let mut j = i + 1;
            let mut hashes = 0;
            while c.get(j) == Some(&'#') {
                hashes += 1;
                j += 1;
            }
            if c.get(j) != Some(&'"') {
                out.push(c[i]);
                i += 1;
                continue;
            }
            out.push('"');
            j += 1;
            loop {
                if j >= c.len() {
                    break;
                }
                if c[j] == '"' && (0..hashes).all(|h| c.get(j + 1 + h) == Some(&'#')) {
                    j += 1 + hashes;
                    break;
                }
                out.push(blank(c[j]));
                j += 1;
            }
            out.push('"');
            i = j;
        } else if c[i] == '"' {
            out.push('"');
            i += 1;
            while i < c.len() && c[i] != '"' {
                if c[i] == '\\' {
                    out.push(' ');
                    i += 1;
                }
                if i < c.len() {
                    out.push(blank(c[i]));
                    i += 1;
                }
            }
            out.push('"');
            i += 1;
        } else if c[i] == '\'' {
            // A char literal ('x', '\n', '\u{..}'), or a lifetime ('a) left as it is.
            if next == Some('\\') {
                let mut j = i + 2;
                while j < c.len() && c[j] != '\'' {
                    j += 1;
                }
                out.push_str("' '");
                i = j + 1;
            } else if c.get(i + 2) == Some(&'\'') {
                out.push_str("' '");
                i += 3;
            } else {
                out.push('\'');
                i += 1;
            }
        } else {
            out.push(c[i]);
            i += 1;
        }
    }
    out
}

/// A block's delimiters, named so that a brace-counting reader of this file is not misled by
/// the character literals.
const OPEN: char = '\u{7b}';
const CLOSE: char = '\u{7d}';

/// `code` (from [`code_only`]) without the items marked `#[cfg(test)]`: from the attribute to
/// the end of the item's block, or to its `;` when it has none. Newlines are kept.
fn strip_cfg_test(code: &str) -> String {
    let c: Vec<char> = code.chars().collect();
    let marker: Vec<char> = "#[cfg(test)]".chars().collect();
    let mut out = String::with_capacity(code.len());
    let mut i = 0;
    while i < c.len() {
        if c[i..].starts_with(&marker) {
            let j = item_end(&c, i + marker.len());
            out.extend(c[i..(j + 1).min(c.len())].iter().filter(|&&ch| ch == '\n'));
            i = j + 1;
        } else {
            out.push(c[i]);
            i += 1;
        }
    }
    out
}

/// The index of the last character of the item starting at `c[j]`: its `;`, or the end of its
/// block (`c.len()` when unterminated).
fn item_end(c: &[char], mut j: usize) -> usize {
    while j < c.len() && c[j] != OPEN && c[j] != ';' {
        j += 1;
    }
    if j < c.len() && c[j] == OPEN {
        let mut depth = 0;
        while j < c.len() {
            match c[j] {
                OPEN => depth += 1,
                CLOSE => {
                    depth -= 1;
                    if depth == 0 {
                        break;
                    }
                }
                _ => {}
            }
            j += 1;
        }
    }
    j
}

fn is_ident(ch: char) -> bool {
    ch.is_alphanumeric() || ch == '_'
}

fn ident_at(c: &[char], mut i: usize) -> (String, usize) {
    while i < c.len() && c[i].is_whitespace() {
        i += 1;
    }
    let start = i;
    while i < c.len() && is_ident(c[i]) {
        i += 1;
    }
    (c[start..i].iter().collect(), i)
}

/// The top-level modules a path starting at `c[i]` (just after `crate::`) names: one, or the
/// first segment of each item of a `{a, b::c}` group.
fn targets_at(c: &[char], i: usize) -> Vec<String> {
    let mut j = i;
    while j < c.len() && c[j].is_whitespace() {
        j += 1;
    }
    if c.get(j) != Some(&OPEN) {
        let (id, _) = ident_at(c, j);
        return vec![id];
    }
    // A group: the first identifier after the opening brace and after every comma at depth one.
    let mut out = Vec::new();
    let mut depth = 0;
    let mut expect = false;
    while j < c.len() {
        match c[j] {
            OPEN => {
                depth += 1;
                if depth == 1 {
                    expect = true;
                }
            }
            CLOSE => {
                depth -= 1;
                if depth == 0 {
                    break;
                }
            }
            ',' if depth == 1 => expect = true,
            ch if expect && is_ident(ch) => {
                let (id, end) = ident_at(c, j);
                out.push(id);
                expect = false;
                j = end;
                continue;
            }
            _ => {}
        }
        j += 1;
    }
    out
}

/// The `crate::` references of one file's code (comments, literals and test items already
/// removed). `module_path` is the file's module path from the crate root (`["sim", "glitch"]`
/// for `src/sim/glitch.rs`), for `super::` chains that leave the top-level module.
fn imports_of(file: &str, module_path: &[String], code: &str) -> Vec<Import> {
    let c: Vec<char> = code.chars().collect();
    let from = module_path[0].clone();
    let lines: Vec<&str> = code.lines().collect();
    let mut out = Vec::new();
    let mut line = 1;
    let mut i = 0;
    let starts = |i: usize, w: &str| -> bool {
        let w: Vec<char> = w.chars().collect();
        c[i..].starts_with(&w) && (i == 0 || !(is_ident(c[i - 1]) || c[i - 1] == '$'))
    };
    while i < c.len() {
        if c[i] == '\n' {
            line += 1;
            i += 1;
            continue;
        }
        let mut targets = Vec::new();
        let mut skip = 1;
        if starts(i, "crate::") {
            targets = targets_at(&c, i + "crate::".len());
            skip = "crate::".len();
        } else if starts(i, "super::") {
            // Count the chain; it reaches the crate root after as many `super`s as the file's
            // module depth.
            let mut j = i;
            let mut n = 0;
            while c[j..].starts_with(&"super::".chars().collect::<Vec<_>>()) {
                n += 1;
                j += "super::".len();
            }
            if n >= module_path.len() {
                targets = targets_at(&c, j);
            }
            skip = j - i;
        }
        for to in targets {
            if !to.is_empty() && to != from {
                out.push(Import {
                    file: file.to_string(),
                    line,
                    from: from.clone(),
                    to,
                    text: lines.get(line - 1).unwrap_or(&"").trim().to_string(),
                });
            }
        }
        i += skip;
    }
    out
}

/// Every `.rs` file under `dir`, with its path relative to `root`.
fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", dir.display()))
        .map(|e| e.expect("directory entry").path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The module path of `rel` (a path under `src/`): `sim/glitch.rs` -> [sim, glitch],
/// `sim/mod.rs` -> [sim], `setup.rs` -> [setup].
fn module_path(rel: &Path) -> Vec<String> {
    let mut parts: Vec<String> = rel
        .iter()
        .map(|s| s.to_string_lossy().trim_end_matches(".rs").to_string())
        .collect();
    if parts.last().is_some_and(|s| s == "mod") {
        parts.pop();
    }
    parts
}

/// Every import of the crate's code under `src` (lib.rs, main.rs and this file aside).
fn crate_imports(src: &Path) -> Vec<Import> {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    let mut out = Vec::new();
    for p in files {
        let rel = p.strip_prefix(src).expect("under src");
        let path = module_path(rel);
        if matches!(path[0].as_str(), "lib" | "main" | "layers") {
            continue;
        }
        let text = std::fs::read_to_string(&p)
            .unwrap_or_else(|e| panic!("cannot read {}: {e}", p.display()));
        let code = strip_cfg_test(&code_only(&text));
        out.extend(imports_of(&format!("src/{}", rel.display()), &path, &code));
    }
    out
}

/// What breaks the order: modules missing from [`LAYERS`], imports of a higher level, and
/// cycles between modules, each naming a file, line and import.
fn violations(imports: &[Import], modules: &BTreeSet<String>) -> Vec<String> {
    let mut out = Vec::new();
    for m in modules {
        if level(m).is_none() {
            out.push(format!("module {m} is not in LAYERS: give it a level"));
        }
    }
    let mut edges: BTreeMap<&str, BTreeMap<&str, &Import>> = BTreeMap::new();
    for imp in imports {
        edges
            .entry(&imp.from)
            .or_default()
            .entry(&imp.to)
            .or_insert(imp);
        if let (Some(a), Some(b)) = (level(&imp.from), level(&imp.to)) {
            if b > a {
                out.push(format!(
                    "{}:{}: {} (level {a}) imports {} (level {b}, above it): `{}`",
                    imp.file, imp.line, imp.from, imp.to, imp.text
                ));
            }
        }
    }
    // Cycles: a depth-first search from every module; a back edge closes one.
    fn visit<'a>(
        m: &'a str,
        edges: &BTreeMap<&'a str, BTreeMap<&'a str, &'a Import>>,
        stack: &mut Vec<&'a str>,
        done: &mut BTreeSet<&'a str>,
        out: &mut Vec<String>,
    ) {
        if done.contains(m) {
            return;
        }
        if let Some(k) = stack.iter().position(|s| *s == m) {
            let cycle: Vec<&str> = stack[k..].iter().copied().chain([m]).collect();
            let how: Vec<String> = cycle
                .windows(2)
                .map(|w| {
                    let imp = edges[w[0]][w[1]];
                    format!("{}:{}: `{}`", imp.file, imp.line, imp.text)
                })
                .collect();
            out.push(format!("cycle {}: {}", cycle.join(" -> "), how.join("; ")));
            return;
        }
        stack.push(m);
        if let Some(next) = edges.get(m) {
            for n in next.keys() {
                visit(n, edges, stack, done, out);
            }
        }
        stack.pop();
        done.insert(m);
    }
    let mut done = BTreeSet::new();
    for m in edges.keys() {
        visit(m, &edges, &mut Vec::new(), &mut done, &mut out);
    }
    out
}

fn src_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/src"))
}

/// The top-level modules: every `src/*.rs` and `src/*/` but lib.rs, main.rs and this file.
fn top_level_modules(src: &Path) -> BTreeSet<String> {
    std::fs::read_dir(src)
        .expect("src")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.is_dir() || p.extension().is_some_and(|x| x == "rs"))
        .map(|p| module_path(p.strip_prefix(src).expect("under src"))[0].clone())
        .filter(|m| !matches!(m.as_str(), "lib" | "main" | "layers"))
        .collect()
}

/// The crate's own tree against the documented order (oracle: [`LAYERS`]).
#[test]
fn layers_are_acyclic_and_point_down() {
    let src = src_dir();
    let imports = crate_imports(&src);
    assert!(
        imports.len() > 100,
        "only {} crate:: imports found under {}: the scan is broken",
        imports.len(),
        src.display()
    );
    let bad = violations(&imports, &top_level_modules(&src));
    assert!(bad.is_empty(), "layer order broken:\n{}", bad.join("\n"));
}

/// The import graph, one line per module (`cargo test --lib layers -- --nocapture` prints it).
#[test]
fn layers_graph_lists_every_module() {
    let src = src_dir();
    let mut graph: BTreeMap<String, BTreeSet<String>> = top_level_modules(&src)
        .into_iter()
        .map(|m| (m, BTreeSet::new()))
        .collect();
    for imp in crate_imports(&src) {
        graph.entry(imp.from).or_default().insert(imp.to);
    }
    let mut by_level: Vec<(&String, &BTreeSet<String>)> = graph.iter().collect();
    by_level.sort_by_key(|(m, _)| level(m));
    for (m, to) in by_level {
        let to: Vec<&str> = to.iter().map(|s| s.as_str()).collect();
        println!("{m} -> {}", to.join(", "));
    }
    // Every layer module exists (a renamed module must be renamed in LAYERS too).
    for m in LAYERS.iter().flat_map(|l| l.iter()) {
        assert!(graph.contains_key(*m), "LAYERS names {m}, which src/ lacks");
    }
}

/// The checker on sources whose answer is known by construction: an upward import, a cycle
/// between two modules of one level, a `use crate::{..}` group, a `super::super` path, and
/// paths in comments, strings and `#[cfg(test)]` items that must not count.
#[test]
fn layers_checker_finds_known_violations() {
    let files = [
        (
            "model/spec.rs",
            "use crate::setup::Error; // crate::cli in a comment\nfn f() { let s = \"crate::cli\"; }\n",
        ),
        (
            "noise/mod.rs",
            "use crate::{io, numerics::fft};\n#[cfg(test)]\nmod tests { use crate::diagnose::X; }\n",
        ),
        ("io/table.rs", "fn g() { super::super::noise::f(); }\n"),
        ("fit/mod.rs", "use crate::model::X;\n"),
    ];
    let mut imports = Vec::new();
    for (f, text) in files {
        let path = module_path(Path::new(f));
        let code = strip_cfg_test(&code_only(text));
        imports.extend(imports_of(f, &path, &code));
    }
    let pairs: Vec<(&str, &str)> = imports
        .iter()
        .map(|i| (i.from.as_str(), i.to.as_str()))
        .collect();
    assert_eq!(
        pairs,
        [
            ("model", "setup"),
            ("noise", "io"),
            ("noise", "numerics"),
            ("io", "noise"),
            ("fit", "model"),
        ]
    );
    let modules: BTreeSet<String> = ["model", "noise", "io", "fit", "setup", "numerics"]
        .map(String::from)
        .into();
    let bad = violations(&imports, &modules);
    assert_eq!(bad.len(), 2, "{bad:#?}");
    assert!(bad[0].starts_with("model/spec.rs:1: model (level 3) imports setup (level 7"));
    assert!(bad[1].starts_with("cycle io -> noise -> io: io/table.rs:1:"));
}
