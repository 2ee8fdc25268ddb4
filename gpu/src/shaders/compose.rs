//! The WGSL preprocessor: modules that name the modules they use on `// #import NAME` lines,
//! composed into one shader text.
//!
//! [`compose`] writes each module reachable from the roots once, every module after the modules
//! it imports (depth first, in the order of the import lines, then of the roots), its
//! `// #import` lines left out and a `// #module NAME` line before it. The result is plain
//! WGSL: what a device compiles and what the web page loads. An import of a module that does not
//! exist, an import cycle, a malformed import line or two modules of one name are errors.
//!
//! Standard library only: the crate's build script compiles this file too (`build.rs`), to
//! compose the render shader when the crate builds.

use std::fmt;

/// What opens an import line (after leading white space).
pub const IMPORT: &str = "// #import";

/// What opens the line [`compose`] writes before each module's text.
pub const MODULE: &str = "// #module";

/// Why modules could not be composed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ComposeError {
    /// `importer` (`None`: the roots) names a module that is not among the modules.
    Missing {
        name: String,
        importer: Option<String>,
    },
    /// The modules import each other in a cycle: the path from the first module of the cycle
    /// back to it.
    Cycle(Vec<String>),
    /// An import line of `module` that names no module, or more than one: `line` (1-based).
    BadImport {
        module: String,
        line: usize,
        text: String,
    },
    /// Two modules have this name.
    Duplicate(String),
}

impl fmt::Display for ComposeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ComposeError::Missing { name, importer } => match importer {
                Some(by) => write!(f, "module `{by}` imports `{name}`, which does not exist"),
                None => write!(f, "no module `{name}`"),
            },
            ComposeError::Cycle(path) => {
                write!(f, "modules import each other in a cycle: {}", path.join(" -> "))
            }
            ComposeError::BadImport { module, line, text } => write!(
                f,
                "module `{module}`, line {line}: `{text}` is not `{IMPORT} NAME` with one module name"
            ),
            ComposeError::Duplicate(name) => write!(f, "two modules are named `{name}`"),
        }
    }
}

impl std::error::Error for ComposeError {}

/// The modules `text` imports, in the order of its import lines.
pub fn imports<'t>(module: &str, text: &'t str) -> Result<Vec<&'t str>, ComposeError> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let Some(rest) = line.trim_start().strip_prefix(IMPORT) else {
            continue;
        };
        let name = rest.trim();
        let valid = !name.is_empty()
            && rest.starts_with(char::is_whitespace)
            && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
        if !valid {
            return Err(ComposeError::BadImport {
                module: module.to_string(),
                line: i + 1,
                text: line.trim().to_string(),
            });
        }
        out.push(name);
    }
    Ok(out)
}

/// Whether `line` is an import line.
fn is_import(line: &str) -> bool {
    line.trim_start().starts_with(IMPORT)
}

/// The names of the modules [`compose`] writes for `roots`, in its order.
pub fn order<'m>(
    modules: &[(&'m str, &'m str)],
    roots: &[&str],
) -> Result<Vec<&'m str>, ComposeError> {
    for (i, (name, _)) in modules.iter().enumerate() {
        if modules[..i].iter().any(|(n, _)| n == name) {
            return Err(ComposeError::Duplicate(name.to_string()));
        }
    }
    let find = |name: &str, importer: Option<&str>| {
        modules
            .iter()
            .find(|(n, _)| *n == name)
            .copied()
            .ok_or_else(|| ComposeError::Missing {
                name: name.to_string(),
                importer: importer.map(str::to_string),
            })
    };
    // Depth first with an explicit stack of (module, its imports, the next import to visit), so
    // that a module is written once all its imports are.
    let mut done: Vec<&'m str> = Vec::new();
    for root in roots {
        let (name, text) = find(root, None)?;
        if done.contains(&name) {
            continue;
        }
        let mut stack = vec![(name, imports(name, text)?, 0usize)];
        while let Some(top) = stack.last_mut() {
            let (module, deps, next) = (top.0, &top.1, top.2);
            match deps.get(next) {
                None => {
                    done.push(module);
                    stack.pop();
                }
                Some(&dep) => {
                    top.2 += 1;
                    let (dep, text) = find(dep, Some(module))?;
                    if done.contains(&dep) {
                        continue;
                    }
                    if let Some(at) = stack.iter().position(|(m, _, _)| *m == dep) {
                        let mut path: Vec<String> =
                            stack[at..].iter().map(|(m, _, _)| m.to_string()).collect();
                        path.push(dep.to_string());
                        return Err(ComposeError::Cycle(path));
                    }
                    stack.push((dep, imports(dep, text)?, 0));
                }
            }
        }
    }
    Ok(done)
}

/// The shader text of `roots` and every module they import, directly or not, from `modules`
/// (name, text): a first line naming the roots, then each module once, in [`order`], as a
/// `// #module NAME` line and the module's text without its import lines (and without a blank
/// line that follows them and one before them).
pub fn compose(modules: &[(&str, &str)], roots: &[&str]) -> Result<String, ComposeError> {
    let names = order(modules, roots)?;
    let mut out = format!(
        "// Composed from WGSL modules by msth-gpu (`shaders::compose`), roots: {}.\n",
        roots.join(", ")
    );
    for name in names {
        let text = modules
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, t)| *t)
            .unwrap_or_default();
        out.push('\n');
        out.push_str(&format!("{MODULE} {name}\n"));
        // A blank line after import lines is dropped when one was written just before them.
        let (mut blank, mut dropped) = (false, false);
        for line in text.lines() {
            if is_import(line) {
                dropped = true;
                continue;
            }
            let is_blank = line.trim().is_empty();
            if !(is_blank && blank && dropped) {
                out.push_str(line);
                out.push('\n');
            }
            (blank, dropped) = (is_blank, false);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: &str = "// a\nconst A: u32 = 1u;\n";
    const B: &str = "// b\n// #import a\nconst B: u32 = A;\n";
    const C: &str = "// #import a\n// #import b\nconst C: u32 = A + B;\n";

    #[test]
    fn imports_come_first_and_each_module_once() {
        let modules = [("c", C), ("b", B), ("a", A)];
        assert_eq!(order(&modules, &["c"]).unwrap(), ["a", "b", "c"]);
        // `a` is imported by `b` and `c`, and is a root too: written once, before both.
        assert_eq!(order(&modules, &["c", "a", "b"]).unwrap(), ["a", "b", "c"]);
        assert_eq!(order(&modules, &["a"]).unwrap(), ["a"]);
        let text = compose(&modules, &["c"]).unwrap();
        assert_eq!(
            text,
            "// Composed from WGSL modules by msth-gpu (`shaders::compose`), roots: c.\n\
             \n// #module a\n// a\nconst A: u32 = 1u;\n\
             \n// #module b\n// b\nconst B: u32 = A;\n\
             \n// #module c\nconst C: u32 = A + B;\n"
        );
        assert_eq!(text.matches("const A").count(), 1);
        assert!(!text.contains(IMPORT));
    }

    #[test]
    fn import_lines_leave_no_double_blank_line() {
        let m = "// m\n\n// #import a\n// #import b\n\nfn m() {}\n\n\nfn n() {}\n";
        let modules = [("m", m), ("a", "a\n"), ("b", "b\n")];
        assert!(compose(&modules, &["m"])
            .unwrap()
            .ends_with("// #module m\n// m\n\nfn m() {}\n\n\nfn n() {}\n"));
    }

    #[test]
    fn roots_and_imports_keep_their_order() {
        let x = "// #import z\n// #import y\nx\n";
        let modules = [("x", x), ("y", "y"), ("z", "z"), ("w", "w")];
        assert_eq!(order(&modules, &["w", "x"]).unwrap(), ["w", "z", "y", "x"]);
        assert_eq!(order(&modules, &["y", "x"]).unwrap(), ["y", "z", "x"]);
        // A module without a final newline still ends its line.
        assert!(compose(&modules, &["y", "z"])
            .unwrap()
            .ends_with("#module y\ny\n\n// #module z\nz\n"));
    }

    #[test]
    fn a_missing_module_is_an_error_naming_its_importer() {
        let modules = [("b", B)];
        let e = compose(&modules, &["b"]).unwrap_err();
        assert_eq!(
            e,
            ComposeError::Missing {
                name: "a".into(),
                importer: Some("b".into())
            }
        );
        assert_eq!(
            e.to_string(),
            "module `b` imports `a`, which does not exist"
        );
        let e = compose(&modules, &["nope"]).unwrap_err();
        assert_eq!(e.to_string(), "no module `nope`");
    }

    #[test]
    fn a_cycle_is_an_error_naming_its_path() {
        let modules = [
            ("top", "// #import p\n"),
            ("p", "// #import q\n"),
            ("q", "// #import r\n"),
            ("r", "// #import p\n"),
        ];
        let e = compose(&modules, &["top"]).unwrap_err();
        assert_eq!(
            e,
            ComposeError::Cycle(vec!["p".into(), "q".into(), "r".into(), "p".into()])
        );
        assert_eq!(
            e.to_string(),
            "modules import each other in a cycle: p -> q -> r -> p"
        );
        let own = [("s", "// #import s\n")];
        assert_eq!(
            compose(&own, &["s"]).unwrap_err(),
            ComposeError::Cycle(vec!["s".into(), "s".into()])
        );
    }

    #[test]
    fn malformed_imports_and_duplicate_names_are_errors() {
        for (text, line) in [
            ("x\n// #import\n", 2),
            ("// #import a b\n", 1),
            ("// #importa\n", 1),
            ("  // #import a;\n", 1),
        ] {
            let modules = [("m", text), ("a", A)];
            let e = compose(&modules, &["m"]).unwrap_err();
            assert!(
                matches!(&e, ComposeError::BadImport { module, line: l, .. } if module == "m" && *l == line),
                "{text:?}: {e:?}"
            );
        }
        // Indented import lines are import lines.
        let modules = [("m", "    // #import a\nm\n"), ("a", A)];
        assert_eq!(order(&modules, &["m"]).unwrap(), ["a", "m"]);
        let twice = [("a", A), ("a", B)];
        assert_eq!(
            compose(&twice, &["a"]).unwrap_err(),
            ComposeError::Duplicate("a".into())
        );
    }
}
