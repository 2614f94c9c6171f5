//! The crate's layers, held: every module's imports of the crate (`crate::…` and `super::…`
//! paths in its code, not in its comments nor in its tests) go to its own layer or one below,
//! `config` imports nothing of the crate, and no module reaches itself through its imports.
//!
//! Layers, bottom up (`lib.rs`'s module doc says what each is for):
//! 0. `config`, `error`, `shutdown`, `clock`, `sync`;
//! 1. `state`;
//! 2. `sample_path`;
//! 3. `services`;
//! 4. the crate root (`lib.rs`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The layer of a top-level module.
fn layer(top: &str) -> Option<usize> {
    Some(match top {
        "config" | "error" | "shutdown" | "clock" | "sync" => 0,
        "state" => 1,
        "sample_path" => 2,
        "services" => 3,
        "crate" => 4,
        _ => return None,
    })
}

/// A module's path (`sample_path::worker`, or `crate` for the root) from its file under `src`.
fn module_of(relative: &Path) -> String {
    let mut parts: Vec<String> = relative
        .iter()
        .map(|p| p.to_string_lossy().trim_end_matches(".rs").to_owned())
        .collect();
    if parts.last().is_some_and(|p| p == "mod") {
        parts.pop();
    }
    if parts == ["lib"] {
        return "crate".to_owned();
    }
    parts.join("::")
}

/// The code of a file: comments, string literals and `#[cfg(test)]` items cut out.
fn code_of(text: &str) -> String {
    let bytes = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < bytes.len() {
        let rest = &text[i..];
        if rest.starts_with("//") {
            i += rest.find('\n').unwrap_or(rest.len());
        } else if rest.starts_with("/*") {
            i += rest.find("*/").map_or(rest.len(), |e| e + 2);
        } else if let Some(len) = char_literal(rest) {
            out.push_str("' '");
            i += len;
        } else if rest.starts_with("r#\"") {
            i += rest.find("\"#").map_or(rest.len(), |e| e + 2);
            out.push_str("\"\"");
        } else if rest.starts_with('"') {
            // A plain string: skip to its unescaped end.
            let mut j = 1;
            while j < rest.len() && rest.as_bytes()[j] != b'"' {
                j += if rest.as_bytes()[j] == b'\\' { 2 } else { 1 };
            }
            out.push_str("\"\"");
            i += (j + 1).min(rest.len());
        } else if rest.starts_with("#[cfg(test)]") {
            i += skip_item(rest);
        } else {
            let c = rest.chars().next().unwrap_or(' ');
            out.push(c);
            i += c.len_utf8();
        }
    }
    out
}

/// The length of the character literal `rest` starts with (`'x'`, `'\\n'`), if it does (a
/// lifetime is not one).
fn char_literal(rest: &str) -> Option<usize> {
    let mut chars = rest.char_indices();
    (chars.next()? == (0, '\'')).then_some(())?;
    let (_, c) = chars.next()?;
    if c == '\\' {
        chars.next()?;
        // `'\u{…}'` and `'\x7f'` run to the next quote.
        return rest[1..].find('\'').map(|e| e + 2).filter(|&n| n <= 12);
    }
    let (at, close) = chars.next()?;
    (close == '\'').then_some(at + 1)
}

/// The length of the attribute and the item after it: to its `;`, or to the brace closing its
/// first brace.
fn skip_item(rest: &str) -> usize {
    let mut depth = 0usize;
    for (at, c) in rest.char_indices().skip("#[cfg(test)]".len()) {
        match c {
            '{' => depth += 1,
            '}' => {
                depth = depth.saturating_sub(1);
                if depth == 0 {
                    return at + 1;
                }
            }
            ';' if depth == 0 => return at + 1,
            _ => {}
        }
    }
    rest.len()
}

/// The crate paths `code` names, each as the list of its segments from the crate root;
/// `use` groups (`crate::{a, b::c}`) are expanded. `module` is the module the code is in.
fn paths_named(code: &str, module: &str) -> Vec<Vec<String>> {
    let here: Vec<String> = match module {
        "crate" => Vec::new(),
        m => m.split("::").map(str::to_owned).collect(),
    };
    // A path may start at a module this one declares (`mod worker;` … `worker::run`).
    let children = children_declared(code);
    let mut found = Vec::new();
    let chars: Vec<char> = code.chars().collect();
    let mut i = 0;
    while i < chars.len() {
        let word_start = i == 0
            || !(chars[i - 1].is_alphanumeric() || chars[i - 1] == '_' || chars[i - 1] == ':');
        let starts = |w: &str| chars[i..].iter().take(w.len()).copied().eq(w.chars());
        let child = children.iter().find(|c| starts(&format!("{c}::")));
        let base = if word_start && starts("crate::") {
            i += "crate::".len();
            Some(Vec::new())
        } else if word_start && starts("self::") {
            i += "self::".len();
            Some(here.clone())
        } else if let (Some(_), true) = (child, word_start) {
            Some(here.clone())
        } else if word_start && starts("super::") {
            let mut base = here.clone();
            while chars[i..].iter().take(7).copied().eq("super::".chars()) {
                base.pop();
                i += "super::".len();
            }
            Some(base)
        } else {
            None
        };
        match base {
            Some(base) => {
                let (tails, end) = tree(&chars, i);
                for tail in tails {
                    let mut p = base.clone();
                    p.extend(tail);
                    found.push(p);
                }
                i = end;
            }
            None => i += 1,
        }
    }
    found
}

/// The modules `code` declares (`mod x;`, `pub mod x;`, `pub(crate) mod x;`).
fn children_declared(code: &str) -> Vec<String> {
    let words: Vec<&str> = code
        .split(|c: char| !(c.is_alphanumeric() || c == '_' || c == ';'))
        .filter(|w| !w.is_empty())
        .collect();
    words
        .windows(2)
        .filter(|w| w[0] == "mod" && w[1].ends_with(';'))
        .map(|w| w[1].trim_end_matches(';').to_owned())
        .collect()
}

/// The paths of a `use` tree starting at `i` (`a::b`, `a::{b, c::d}`), and where it ends.
fn tree(chars: &[char], mut i: usize) -> (Vec<Vec<String>>, usize) {
    let mut prefix = Vec::new();
    loop {
        if chars.get(i) == Some(&'{') {
            let mut all = Vec::new();
            i += 1;
            loop {
                while chars.get(i).is_some_and(|c| c.is_whitespace() || *c == ',') {
                    i += 1;
                }
                if chars.get(i).is_none_or(|c| *c == '}') {
                    return (all, i + 1);
                }
                let (tails, end) = tree(chars, i);
                for t in tails {
                    let mut p = prefix.clone();
                    p.extend(t);
                    all.push(p);
                }
                i = end;
            }
        }
        let start = i;
        while chars
            .get(i)
            .is_some_and(|c| c.is_alphanumeric() || *c == '_')
        {
            i += 1;
        }
        let word: String = chars[start..i].iter().collect();
        if word.is_empty() {
            return (vec![prefix], i);
        }
        prefix.push(word);
        if chars[i..].iter().take(2).copied().eq("::".chars()) {
            i += 2;
        } else {
            return (vec![prefix], i);
        }
    }
}

/// Each module of the crate under `src` with the modules its code imports: the longest
/// module path each named path starts with (an item re-exported by a module counts as that
/// module's).
fn imports(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let mut files = Vec::new();
    collect(src, &mut files);
    let modules: BTreeSet<String> = files
        .iter()
        .map(|f| module_of(f.strip_prefix(src).unwrap_or(f)))
        .collect();
    let mut graph = BTreeMap::new();
    for file in &files {
        let module = module_of(file.strip_prefix(src).unwrap_or(file));
        let text = std::fs::read_to_string(file).unwrap_or_default();
        let mut to = BTreeSet::new();
        for path in paths_named(&code_of(&text), &module) {
            let target = (0..=path.len())
                .rev()
                .map(|n| match n {
                    0 => "crate".to_owned(),
                    n => path[..n].join("::"),
                })
                .find(|m| modules.contains(m) || m == "crate")
                .unwrap_or_else(|| "crate".to_owned());
            if target != module {
                to.insert(target);
            }
        }
        graph.insert(module, to);
    }
    graph
}

fn collect(dir: &Path, files: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if path.is_dir() && name != "bin" {
            collect(&path, files);
        } else if name.ends_with(".rs") && name != "main.rs" && name != "layers.rs" {
            files.push(path);
        }
    }
}

fn top(module: &str) -> &str {
    module.split("::").next().unwrap_or(module)
}

/// What breaks the rules in `graph`: an import upward, `config` importing anything of the
/// crate, a module outside every layer, and each cycle (as the path that closes it).
fn violations(graph: &BTreeMap<String, BTreeSet<String>>) -> Vec<String> {
    let mut v = Vec::new();
    for (from, tos) in graph {
        let Some(from_layer) = layer(top(from)) else {
            v.push(format!("{from}: in no layer (add it to `layer`)"));
            continue;
        };
        if top(from) == "config" && !tos.is_empty() {
            v.push(format!(
                "{from} imports {tos:?}: the settings import nothing of the crate"
            ));
        }
        for to in tos {
            if layer(top(to)).is_some_and(|l| l > from_layer) {
                v.push(format!("{from} imports {to}, a layer above it"));
            }
        }
    }
    // Depth-first, in order: a module met again while still on the stack closes a cycle.
    #[derive(Clone, Copy, PartialEq)]
    enum Mark {
        Open,
        Done,
    }
    fn visit(
        m: &str,
        graph: &BTreeMap<String, BTreeSet<String>>,
        marks: &mut BTreeMap<String, Mark>,
        stack: &mut Vec<String>,
        cycles: &mut Vec<String>,
    ) {
        match marks.get(m) {
            Some(Mark::Done) => return,
            Some(Mark::Open) => {
                let at = stack.iter().position(|s| s == m).unwrap_or(0);
                let mut cycle = stack[at..].to_vec();
                cycle.push(m.to_owned());
                cycles.push(format!("cycle: {}", cycle.join(" → ")));
                return;
            }
            None => {}
        }
        marks.insert(m.to_owned(), Mark::Open);
        stack.push(m.to_owned());
        for to in graph.get(m).into_iter().flatten() {
            visit(to, graph, marks, stack, cycles);
        }
        stack.pop();
        marks.insert(m.to_owned(), Mark::Done);
    }
    let mut marks = BTreeMap::new();
    for m in graph.keys() {
        visit(m, graph, &mut marks, &mut Vec::new(), &mut v);
    }
    v
}

#[test]
fn the_gateway_is_layered_and_acyclic() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let graph = imports(&src);
    // The reading itself: a graph of this crate that lost its modules proves nothing.
    for m in [
        "config",
        "state::sensors",
        "sample_path::worker",
        "services::backfill",
    ] {
        assert!(graph.contains_key(m), "{m} not found in {graph:?}");
    }
    assert!(graph["sample_path::worker"].contains("sample_path::kernel"));
    assert!(graph["services::backfill"].contains("sample_path"));
    let v = violations(&graph);
    assert!(v.is_empty(), "{}", v.join("\n"));
}

#[test]
fn the_reading_finds_groups_super_and_skips_comments_and_tests() {
    let code = code_of(
        "mod k;\nuse crate::{a::{b, c::D}, e};\n// crate::commented\nfn f() { super::g::h(); \
         k::f(); self::k::g(); m::k::n(); \
         \"crate::quoted\"; '\"'; let _: &'static str; }\n#[cfg(test)]\nmod tests { use crate::tested; }\n\
         use crate::after;",
    );
    let mut paths = paths_named(&code, "x::y");
    paths.sort();
    let want: Vec<Vec<String>> = [
        vec!["a", "b"],
        vec!["a", "c", "D"],
        vec!["after"],
        vec!["e"],
        vec!["x", "g", "h"],
        vec!["x", "y", "k", "f"],
        vec!["x", "y", "k", "g"],
    ]
    .iter()
    .map(|p| p.iter().map(|s| s.to_string()).collect())
    .collect();
    assert_eq!(paths, want);
}

#[test]
fn a_cycle_and_an_upward_import_are_found() {
    let graph = |edges: &[(&str, &str)]| {
        let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for (a, b) in edges {
            g.entry(a.to_string()).or_default().insert(b.to_string());
            g.entry(b.to_string()).or_default();
        }
        g
    };
    let ok = graph(&[
        ("services::a", "sample_path"),
        ("sample_path::b", "state"),
        ("crate", "services::a"),
    ]);
    assert!(violations(&ok).is_empty(), "{:?}", violations(&ok));
    let cycle = graph(&[
        ("sample_path::a", "sample_path::b"),
        ("sample_path::b", "sample_path::c"),
        ("sample_path::c", "sample_path::a"),
    ]);
    let v = violations(&cycle);
    assert!(v.iter().any(|s| s.starts_with("cycle: ")), "{v:?}");
    let up = graph(&[("state::x", "services::y")]);
    assert!(violations(&up)[0].contains("a layer above"));
    let settings = graph(&[("config", "clock")]);
    assert!(violations(&settings)[0].contains("import nothing"));
}
