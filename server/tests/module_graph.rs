//! The crate's modules form no cycle: reading every `crate::…` (and `super::…` that reaches the
//! crate root) in `src/`, comments and string literals aside, the graph of top-level modules is
//! acyclic, and `lib.rs`'s Layout list names every module after all those it uses. The binary's
//! commands (`cmd`: serve, eval, health, ceiling) are the top layer: listed last, used by no
//! other module, so the library never depends on a command's flags or output.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Top-level module → the top-level modules its code names.
type Graph = BTreeMap<String, BTreeSet<String>>;

/// `text` with comments, string literals and character literals blanked out.
fn code_only(text: &str) -> String {
    let s: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    while i < s.len() {
        let at = |k: usize| s.get(i + k).copied().unwrap_or('\0');
        if at(0) == '/' && at(1) == '/' {
            while i < s.len() && s[i] != '\n' {
                i += 1;
            }
        } else if at(0) == '/' && at(1) == '*' {
            let mut depth = 0;
            while i < s.len() {
                if s[i] == '/' && s.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if s[i] == '*' && s.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
        } else if at(0) == 'r' && (at(1) == '"' || at(1) == '#') && (i == 0 || !ident(s[i - 1])) {
            // A raw string r"…" or r#"…"# (b before r is harmless).
            let hashes = (1..).take_while(|&k| at(k) == '#').count();
            if at(1 + hashes) != '"' {
                out.push(s[i]);
                i += 1;
                continue;
            }
            i += 2 + hashes;
            while i < s.len() && !(s[i] == '"' && (1..=hashes).all(|k| s.get(i + k) == Some(&'#')))
            {
                i += 1;
            }
            i += 1 + hashes;
        } else if at(0) == '"' {
            i += 1;
            while i < s.len() && s[i] != '"' {
                i += if s[i] == '\\' { 2 } else { 1 };
            }
            i += 1;
        } else if at(0) == '\'' && at(1) == '\\' {
            i += 2;
            while i < s.len() && s[i] != '\'' {
                i += 1;
            }
            i += 1;
        } else if at(0) == '\'' && at(2) == '\'' {
            i += 3;
        } else {
            out.push(s[i]);
            i += 1;
        }
    }
    out
}

/// The first identifier of each path in `crate::<rest>`: `a` of `a::b`, `a` and `c` of
/// `{a::b, c}`.
fn heads(rest: &str) -> Vec<String> {
    let rest = rest.trim_start();
    let ident = |t: &str| -> String {
        t.trim_start()
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect()
    };
    let Some(group) = rest.strip_prefix('{') else {
        return vec![ident(rest)];
    };
    let (mut depth, mut items, mut start) = (0, Vec::new(), 0);
    for (k, c) in group.char_indices() {
        match c {
            '{' => depth += 1,
            '}' if depth == 0 => {
                items.push(&group[start..k]);
                break;
            }
            '}' => depth -= 1,
            ',' if depth == 0 => {
                items.push(&group[start..k]);
                start = k + 1;
            }
            _ => {}
        }
    }
    items.into_iter().map(ident).collect()
}

/// The modules `lib.rs` declares, in order (`pub mod x;` and inline `pub mod x { … }`).
fn declared(lib: &str) -> Vec<String> {
    code_only(lib)
        .lines()
        .filter_map(|l| l.trim().strip_prefix("pub mod "))
        .map(|rest| heads(rest).remove(0))
        .collect()
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// Which top-level module each file's code names.
fn graph(src: &Path, modules: &BTreeSet<String>) -> Graph {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    let mut graph = Graph::new();
    for file in files {
        // The module path of the file: `session/envs.rs` is session::envs, `service/mod.rs` is
        // service. lib.rs declares the modules; main.rs is the binary, another crate.
        let relative = file.strip_prefix(src).unwrap().with_extension("");
        let mut path: Vec<String> = relative
            .iter()
            .map(|c| c.to_string_lossy().into_owned())
            .collect();
        if path.last().is_some_and(|p| p == "mod") {
            path.pop();
        }
        if path == ["lib"] || path == ["main"] {
            continue;
        }
        let from = path[0].clone();
        let code = code_only(&std::fs::read_to_string(&file).unwrap());
        let mut uses = Vec::new();
        for (at, _) in code.match_indices("crate::") {
            if code[..at].ends_with(|c: char| c.is_alphanumeric() || c == '_' || c == '$') {
                continue;
            }
            uses.extend(heads(&code[at + "crate::".len()..]));
        }
        for (at, _) in code.match_indices("super::") {
            if code[..at].ends_with("super::")
                || code[..at].ends_with(|c: char| c.is_alphanumeric() || c == '_')
            {
                continue;
            }
            // `super::super::x` from a::b::c is x at the root: a top-level module.
            let mut rest = &code[at..];
            let mut up = 0;
            while let Some(r) = rest.strip_prefix("super::") {
                rest = r;
                up += 1;
            }
            if up >= path.len() {
                uses.extend(heads(rest));
            }
        }
        let to = graph.entry(from.clone()).or_default();
        to.extend(
            uses.into_iter()
                .filter(|m| modules.contains(m) && *m != from),
        );
    }
    graph
}

/// A cycle of `graph`, if it has one, as the modules along it.
fn cycle(graph: &Graph) -> Option<Vec<String>> {
    fn visit<'a>(
        node: &'a str,
        graph: &'a Graph,
        done: &mut BTreeSet<&'a str>,
        stack: &mut Vec<&'a str>,
    ) -> Option<Vec<String>> {
        if let Some(k) = stack.iter().position(|&n| n == node) {
            let mut found: Vec<String> = stack[k..].iter().map(|n| n.to_string()).collect();
            found.push(node.to_string());
            return Some(found);
        }
        if !done.insert(node) {
            return None;
        }
        stack.push(node);
        for next in graph.get(node).into_iter().flatten() {
            if let Some(found) = visit(next, graph, done, stack) {
                return Some(found);
            }
        }
        stack.pop();
        None
    }
    let mut done = BTreeSet::new();
    graph
        .keys()
        .find_map(|node| visit(node, graph, &mut done, &mut Vec::new()))
}

#[test]
fn the_scanner_reads_code_not_comments_or_strings() {
    let code = code_only(
        "use crate::{a::X, b}; // crate::c\n/* crate::d /* nested */ crate::e */\n\
         let s = \"crate::f\"; let r = r#\"crate::\"g\"#; let q = '\"'; crate::h::y(); 'a: loop {}",
    );
    let found: Vec<String> = code
        .match_indices("crate::")
        .flat_map(|(at, _)| heads(&code[at + 7..]))
        .collect();
    assert_eq!(found, ["a", "b", "h"]);
    let fake: Graph = [("a", "b"), ("b", "c"), ("c", "a")]
        .into_iter()
        .map(|(x, y)| (x.to_string(), BTreeSet::from([y.to_string()])))
        .collect();
    assert_eq!(cycle(&fake).map(|c| c.len()), Some(4));
}

#[test]
fn the_server_modules_form_no_cycle_in_their_layout_order() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let lib = std::fs::read_to_string(src.join("lib.rs")).unwrap();
    let modules: BTreeSet<String> = declared(&lib).into_iter().collect();
    let graph = graph(&src, &modules);
    assert!(
        graph["service"].contains("session") && graph["session"].contains("budget"),
        "the scanner found too little: {graph:?}"
    );
    if let Some(cycle) = cycle(&graph) {
        panic!("module cycle: {}", cycle.join(" -> "));
    }

    // lib.rs's Layout section lists each module (`//! - [`name`]: …`) after those it uses.
    let layout: Vec<&str> = lib
        .lines()
        .filter_map(|l| l.strip_prefix("//! - [`"))
        .filter_map(|l| l.split_once('`').map(|(name, _)| name))
        .collect();
    let listed: BTreeSet<String> = layout.iter().map(|m| m.to_string()).collect();
    assert_eq!(listed, modules, "lib.rs's Layout lists every module once");
    for (i, module) in layout.iter().enumerate() {
        for used in graph.get(*module).into_iter().flatten() {
            assert!(
                layout[..i].contains(&used.as_str()),
                "lib.rs's Layout lists {module} before {used}, which it uses"
            );
        }
    }
    // The commands are the top layer: listed last, and no library module reaches into them.
    assert_eq!(
        layout.last(),
        Some(&"cmd"),
        "lib.rs's Layout lists cmd last"
    );
    assert!(
        graph["cmd"].contains("server") && graph["cmd"].contains("policy"),
        "the scanner found too little under cmd/: {graph:?}"
    );
    for (module, uses) in &graph {
        assert!(
            !uses.contains("cmd"),
            "{module} uses cmd, the binary's commands; move what it needs into the library"
        );
    }
    for module in &layout {
        let uses: Vec<&str> = graph
            .get(*module)
            .into_iter()
            .flatten()
            .map(String::as_str)
            .collect();
        println!("{module} -> {}", uses.join(", "));
    }
}
