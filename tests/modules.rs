//! The module layout holds: within every crate of the workspace, no module imports a sibling (or
//! cousin) that imports it back, so each module's room is clear and a change in one does not
//! ripple through a ring of others. A module's parent may re-export it and the child may use
//! what the parent shares: that is the tree itself, not a cycle. Imports are read from the
//! sources (`crate::…` and `super::…` paths outside comments and test modules).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

type Module = Vec<String>;

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

fn module_of(src: &Path, file: &Path) -> Module {
    let rel = file.strip_prefix(src).unwrap().with_extension("");
    let mut parts: Module = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    if matches!(
        parts.last().map(String::as_str),
        Some("mod" | "lib" | "main")
    ) {
        parts.pop();
    }
    parts
}

/// The code of a file without comment lines and without its test module.
fn code(file: &Path) -> String {
    let text = std::fs::read_to_string(file).unwrap();
    let text = match text.find("#[cfg(test)]") {
        Some(i) => &text[..i],
        None => &text[..],
    };
    text.lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The paths after each occurrence of `prefix` (`crate::` or `super::`), as identifiers.
fn paths_after(code: &str, prefix: &str) -> Vec<(usize, Module)> {
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(i) = rest.find(prefix) {
        let before = rest[..i].chars().last();
        let after = &rest[i + prefix.len()..];
        rest = after;
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
            continue;
        }
        // `super::super::x`: count the levels.
        let mut ups = 1;
        let mut tail = after;
        while prefix == "super::" && tail.starts_with("super::") {
            ups += 1;
            tail = &tail["super::".len()..];
        }
        let path: Module = tail
            .split("::")
            .map(|s| {
                s.chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect::<String>()
            })
            .take_while(|s| !s.is_empty())
            .collect();
        out.push((ups, path));
    }
    out
}

/// Each module of the crate at `dir` and the modules it imports.
fn imports(dir: &Path) -> BTreeMap<Module, BTreeSet<Module>> {
    let src = dir.join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let modules: BTreeSet<Module> = files.iter().map(|f| module_of(&src, f)).collect();
    let resolve = |path: Module| -> Option<Module> {
        (1..=path.len())
            .rev()
            .map(|k| path[..k].to_vec())
            .find(|m| modules.contains(m))
    };
    let mut out = BTreeMap::new();
    for f in &files {
        let me = module_of(&src, f);
        let text = code(f);
        let mut deps = BTreeSet::new();
        for (_, path) in paths_after(&text, "crate::") {
            deps.extend(resolve(path));
        }
        for (ups, path) in paths_after(&text, "super::") {
            if ups > me.len() {
                continue;
            }
            let mut full = me[..me.len() - ups].to_vec();
            full.extend(path);
            deps.extend(resolve(full));
        }
        deps.remove(&me);
        out.insert(me, deps);
    }
    out
}

fn is_ancestor(a: &Module, b: &Module) -> bool {
    a.len() < b.len() && b.starts_with(a)
}

fn crates() -> Vec<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let manifest = std::fs::read_to_string(root.join("Cargo.toml")).unwrap();
    let members = manifest
        .lines()
        .find(|l| l.starts_with("members"))
        .expect("a workspace members line");
    let mut dirs: Vec<PathBuf> = members
        .split('"')
        .skip(1)
        .step_by(2)
        .map(|m| root.join(m))
        .collect();
    dirs.push(root.to_path_buf());
    dirs
}

#[test]
fn no_module_imports_one_that_imports_it_back() {
    let mut cycles = Vec::new();
    let dirs = crates();
    assert!(dirs.len() >= 10, "the workspace's crates: {dirs:?}");
    for dir in dirs {
        let graph = imports(&dir);
        assert!(!graph.is_empty(), "no modules read in {}", dir.display());
        for (a, deps) in &graph {
            for b in deps {
                if a < b
                    && !is_ancestor(a, b)
                    && !is_ancestor(b, a)
                    && graph.get(b).is_some_and(|d| d.contains(a))
                {
                    cycles.push(format!(
                        "{}: {} <-> {}",
                        dir.file_name().unwrap().to_string_lossy(),
                        a.join("::"),
                        b.join("::")
                    ));
                }
            }
        }
    }
    assert!(
        cycles.is_empty(),
        "modules that import each other: {cycles:#?}"
    );
}

#[test]
fn the_import_reader_finds_a_cycle_it_is_shown() {
    // Two sibling modules that import each other, one through `super::`, one through `crate::`.
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("src");
    std::fs::create_dir_all(src.join("format")).unwrap();
    std::fs::write(src.join("lib.rs"), "pub mod format;\n").unwrap();
    std::fs::write(src.join("format/mod.rs"), "pub mod a;\npub mod b;\n").unwrap();
    std::fs::write(
        src.join("format/a.rs"),
        "use super::b::Thing;\n// crate::format::b in a comment does not count\n",
    )
    .unwrap();
    std::fs::write(
        src.join("format/b.rs"),
        "pub struct Thing;\nfn f() { crate::format::a::g(); }\n#[cfg(test)]\nmod t { use crate::x; }\n",
    )
    .unwrap();
    let graph = imports(dir.path());
    let a: Module = vec!["format".into(), "a".into()];
    let b: Module = vec!["format".into(), "b".into()];
    assert!(graph[&a].contains(&b), "{graph:?}");
    assert!(graph[&b].contains(&a), "{graph:?}");
    assert_eq!(graph[&a].len(), 1, "a comment counted: {graph:?}");
}
