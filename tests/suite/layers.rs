//! The modules of `src` form layers: at every level of the tree (the crate's top-level
//! modules, the submodules of each module, and so on down), the dependencies between a
//! module's children form a graph without cycles.
//!
//! How a dependency is found: every file under `src` is read as Rust tokens (comments and
//! string literals skipped, so prose never counts). A dependency is a path that names a
//! module of the crate: `crate::…`, `super::…`, `self::…`, `crispen::…` (the binary's side),
//! a child module's name (`settings::…` in its parent), or a name a `use` brought in for a
//! module; `use` trees (`crate::{a, b::c}`) are expanded; intra-doc links (`[`crate::x`]`,
//! `[text](super::y)`) count too, since the documentation breaks when their target moves.
//! A name a module's `use` brings in is followed to the module that defines it (a child's
//! `super::X` sees its parent's private imports as well as its re-exports); a re-export
//! (`pub use other::X`) is an edge of its own only when the re-exporting file uses `X`. Test code
//! (`#[cfg(test)]`) counts like any other: it is compiled into its module.
//!
//! The granularity: at each level the nodes are the module's children, each with all its
//! descendants (`daemon::store` is one node among `daemon`'s children, and its own children
//! are a level of their own), and the module's own file (`mod.rs`; `lib.rs` and `main.rs`
//! at the top), shown as `daemon::store (root)`. A root that defines what its children use
//! and also calls into them is a cycle like any other: the shared definitions go to a child
//! of their own, which the root re-exports (a re-export alone is no edge, see above). So
//! `daemon → http → daemon` is a cycle at the top level, `daemon::job → daemon::prepare →
//! daemon::job` one among `daemon`'s children, and `mesh (root) → mesh::stl → mesh (root)`
//! one when the root both reads through `stl` and defines the `Mesh` that `stl` returns.
//!
//! Run with `--nocapture` to see every level's graph and its cycles.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::path::{Path, PathBuf};

/// Edges allowed to close a cycle, each with the reason it must. The list stays so a
/// cycle that has to be lived with for a while is named here, with its reason, rather than
/// hidden; an entry that no longer matches an edge fails the test, so it cannot outlive
/// its cycle.
const ALLOWED: &[(&str, &str)] = &[
    // The eject run (issue 43) is one of the supervisor's steps between jobs: it drives
    // the supervisor's link, shows its state and follows its gate, all defined in
    // `daemon/printer.rs`. Those move to a child of their own (`printer::link` or the
    // like) once the copies, maintenance and plates of issues 44 and 45, which reshape
    // the same file, have landed; until then one step of the file is kept out of it.
    ("daemon::printer::eject", "daemon::printer (root)"),
    // The observer's preparation step (issue 46) slices each candidate with the
    // preparation's own slicing (`place`, `slice_job`, `SliceRequest`, `Step`), defined
    // in `daemon/prepare/steps.rs`, which calls it for `strength = "observed"`. The
    // slicing moves to a child of its own with the crate split (issue 47), which takes
    // this layer apart anyway; until then the observer's step is kept out of the file.
    (
        "daemon::prepare::steps::observed",
        "daemon::prepare::steps (root)",
    ),
];

#[test]
fn src_has_no_module_cycle() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    // The farm's crate, and each layer taken out of it (issue 47, every crate under
    // `crates/`): between crates Cargo keeps the order; within each, this test does.
    let mut trees: Vec<(String, &[(&str, &str)])> = vec![("src".to_string(), ALLOWED)];
    let mut crates: Vec<String> = std::fs::read_dir(root.join("crates"))
        .unwrap()
        .map(|e| format!("crates/{}/src", e.unwrap().file_name().to_string_lossy()))
        .collect();
    crates.sort();
    trees.extend(crates.into_iter().map(|c| (c, &[][..])));
    let mut problems = Vec::new();
    for (tree, allowed) in &trees {
        let graph = Graph::scan(&root.join(tree)).unwrap_or_else(|e| panic!("{tree}: {e}"));
        let report = graph.report(allowed);
        println!("{tree}:\n{}", report.text);
        if !report.cycles.is_empty() {
            problems.push(format!(
                "{} module cycle(s) in {tree} (the report above lists every edge with its file and line):\n{}",
                report.cycles.len(),
                report.cycles.join("\n")
            ));
        }
        for stale in &report.stale {
            problems.push(format!(
                "ALLOWED names {} → {}, which is no longer an edge: remove it from tests/suite/layers.rs",
                stale.0, stale.1
            ));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// The checker itself: a small tree with a cycle through a `use` tree, a plain path and an
/// intra-doc link is reported with every edge's file and line; the same tree without the
/// doc link is clean; prose, strings and test modules' `super` do not count.
#[test]
fn the_checker_reports_a_cycle_with_each_edges_place() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("src");
    let write = |path: &str, text: &str| {
        let path = src.join(path);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, text).unwrap();
    };
    write("lib.rs", "pub mod a;\npub mod b;\npub mod c;\n");
    write(
        "a/mod.rs",
        "//! A.\npub mod inner;\nuse crate::{b::Thing, c};\n",
    );
    write("a/inner.rs", "pub fn f() -> u8 { super::super::b::g() }\n");
    write(
        "b.rs",
        "// crate::a::X in a comment\npub struct Thing;\npub fn g() -> u8 {\n    let _ = \"crate::a::inner\";\n    0\n}\n#[cfg(test)]\nmod tests {\n    use super::*;\n}\n",
    );
    let c = "/// Made for [`crate::a::inner::f`].\npub fn h() {}\n/// See `crate::a` (prose, not a link).\npub fn i() {}\n";
    write("c.rs", c);
    let graph = Graph::scan(&src).unwrap();
    let report = graph.report(&[]);
    println!("{}", report.text);
    assert_eq!(report.cycles.len(), 1, "{}", report.text);
    let cycle = &report.cycles[0];
    for place in ["a/mod.rs:3", "c.rs:1"] {
        assert!(cycle.contains(place), "{place} is not named in:\n{cycle}");
    }
    assert!(
        cycle.contains("a → c") && cycle.contains("c → a"),
        "{cycle}"
    );
    assert!(!report.text.contains("b → a"), "{}", report.text);

    // Allowing one edge of the cycle breaks it; allowing an edge that is not there is stale.
    let report = graph.report(&[("c", "a"), ("b", "c")]);
    assert!(report.cycles.is_empty(), "{}", report.text);
    assert_eq!(report.stale, vec![("b".to_string(), "c".to_string())]);

    // Without the doc link there is no cycle.
    write("c.rs", "/// Made for `f`.\npub fn h() {}\n");
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert!(report.cycles.is_empty(), "{}", report.text);

    // A cycle between two children of `c`, one through a re-export in `c`'s own file.
    write("c.rs", "mod d;\nmod e;\npub use d::D;\n");
    write("c/d.rs", "pub struct D(super::e::E);\n");
    write("c/e.rs", "pub struct E;\npub fn f(_: super::D) {}\n");
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert_eq!(report.cycles.len(), 1, "{}", report.text);
    let cycle = &report.cycles[0];
    assert!(
        cycle.starts_with("cycle in `c`: c::d → c::e → c::d")
            && cycle.contains("c/d.rs:1")
            && cycle.contains("c/e.rs:2"),
        "{cycle}"
    );
    // A re-export of a sibling's item is no edge while the re-exporting file does not
    // use the item itself.
    write("c/d.rs", "pub use super::e::E;\npub struct D;\n");
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert!(report.cycles.is_empty(), "{}", report.text);
    write("c/d.rs", "pub use super::e::E;\npub struct D(E);\n");
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert_eq!(report.cycles.len(), 1, "{}", report.text);

    // A root file is a node: defining what a child uses while calling into it is a cycle;
    // the same definition in a child of its own, re-exported by the root, is not.
    write(
        "c.rs",
        "mod d;\nmod e;\npub struct Shared;\npub fn run() { d::go() }\n",
    );
    write("c/d.rs", "pub fn go() { let _ = super::Shared; }\n");
    write("c/e.rs", "pub struct E;\n");
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert_eq!(report.cycles.len(), 1, "{}", report.text);
    assert!(
        report.cycles[0].starts_with("cycle in `c`: c (root) → c::d → c (root)"),
        "{}",
        report.text
    );
    write(
        "c.rs",
        "mod d;\nmod e;\npub use e::Shared;\npub fn run() { d::go() }\n",
    );
    write("c/e.rs", "pub struct Shared;\n");
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert!(report.cycles.is_empty(), "{}", report.text);
    // A private import is followed too (children see it), a visibility restriction
    // (`pub(in crate::c)`) uses nothing, and the root's own documentation linking to its
    // children is its table of contents.
    write(
        "c.rs",
        "//! Runs [`d`].\nmod d;\nmod e;\nuse e::Shared;\npub fn run() { d::go() }\n",
    );
    write("c/e.rs", "pub(in crate::c) struct Shared;\n");
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert!(report.cycles.is_empty(), "{}", report.text);
    // A child's item doc linking to its root is a use: with the root's import of `Shared`,
    // a cycle.
    write(
        "c/e.rs",
        "pub struct Shared;\n/// Not [`super::run`].\npub fn f() {}\n",
    );
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert!(
        report.cycles.iter().any(
            |c| c.starts_with("cycle in `c`: c (root) → c::e → c (root)") && c.contains("c/e.rs:2")
        ),
        "{}",
        report.text
    );

    // A name the root brings in from another crate (`pub use other as m`) leaves the
    // crate: a child's path through it is no edge to the root, even while the root calls
    // into that child. The same name defined in the root is one.
    write(
        "lib.rs",
        "pub use other as m;
pub mod a;
pub fn run() { a::go() }
",
    );
    write(
        "a.rs",
        "pub fn go() { crate::m::work() }
",
    );
    for gone in ["a/mod.rs", "a/inner.rs", "b.rs", "c.rs", "c/d.rs", "c/e.rs"] {
        let _ = std::fs::remove_file(src.join(gone));
    }
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert!(report.cycles.is_empty(), "{}", report.text);
    write(
        "lib.rs",
        "pub mod m { pub fn work() {} }
pub mod a;
pub fn run() { a::go() }
",
    );
    let report = Graph::scan(&src).unwrap().report(&[]);
    assert_eq!(report.cycles.len(), 1, "{}", report.text);
}

// ------------------------------------------------------------------------------ the scan

/// A module's path from the crate root (`[]` is the root: lib.rs and main.rs).
type ModPath = Vec<String>;

/// Where an edge was seen: file (relative to `src`) and line.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct Place {
    file: String,
    line: usize,
}

struct Graph {
    /// Every dependency between file modules, with each place it is written.
    edges: BTreeMap<(ModPath, ModPath), BTreeSet<Place>>,
    modules: BTreeSet<ModPath>,
}

struct Report {
    text: String,
    cycles: Vec<String>,
    stale: Vec<(String, String)>,
}

/// One file, lexed.
struct Source {
    module: ModPath,
    rel: String,
    tokens: Vec<Token>,
    /// Doc comment lines: line number, text, and whether it documents the file's module
    /// itself (`//!`).
    docs: Vec<(usize, String, bool)>,
}

#[derive(Debug, Clone, PartialEq)]
enum Tok {
    Ident(String),
    PathSep,
    Punct(char),
}

#[derive(Debug, Clone)]
struct Token {
    tok: Tok,
    line: usize,
}

impl Token {
    fn ident(&self) -> Option<&str> {
        match &self.tok {
            Tok::Ident(s) => Some(s),
            _ => None,
        }
    }
    fn is(&self, c: char) -> bool {
        self.tok == Tok::Punct(c)
    }
}

/// A path as written, and the module it was written in (including inline modules).
struct Written {
    scope: ModPath,
    segments: Vec<String>,
    line: usize,
}

/// What a file's `use` statements bring in.
struct Use {
    scope: ModPath,
    segments: Vec<String>,
    /// The name it is known by in the file (`as` or the last segment); None for a glob.
    name: Option<String>,
    public: bool,
    line: usize,
}

impl Graph {
    fn scan(src: &Path) -> Result<Graph, String> {
        let mut files = Vec::new();
        walk(src, &mut files)?;
        files.sort();
        let mut sources = Vec::new();
        let mut modules = BTreeSet::new();
        for file in &files {
            let rel = file.strip_prefix(src).unwrap();
            let module = module_of(rel);
            let text = std::fs::read_to_string(file)
                .map_err(|e| format!("{}: cannot read: {e}", file.display()))?;
            let (tokens, docs) = lex(&text).map_err(|e| format!("{}: {e}", file.display()))?;
            modules.insert(module.clone());
            sources.push(Source {
                module,
                rel: rel.display().to_string(),
                tokens,
                docs,
            });
        }
        // First every file's uses (imports are followed when resolving), then the paths.
        let parsed: Vec<(Vec<Use>, Vec<Written>, BTreeSet<String>)> =
            sources.iter().map(|s| s.parse()).collect();
        let mut reexports: BTreeMap<ModPath, BTreeMap<String, Vec<String>>> = BTreeMap::new();
        let mut foreign: BTreeMap<ModPath, BTreeSet<String>> = BTreeMap::new();
        for (source, (uses, _, _)) in sources.iter().zip(&parsed) {
            for u in uses.iter().filter(|u| u.scope == source.module) {
                if let Some(name) = &u.name {
                    match absolute(&modules, &u.scope, &u.segments, &BTreeMap::new()) {
                        Some(abs) => {
                            reexports
                                .entry(source.module.clone())
                                .or_default()
                                .insert(name.clone(), abs);
                        }
                        None => {
                            foreign
                                .entry(source.module.clone())
                                .or_default()
                                .insert(name.clone());
                        }
                    }
                }
            }
        }
        let resolver = Resolver {
            modules: &modules,
            reexports: &reexports,
            foreign: &foreign,
        };
        let mut edges: BTreeMap<(ModPath, ModPath), BTreeSet<Place>> = BTreeMap::new();
        for (source, (uses, written, used_idents)) in sources.iter().zip(&parsed) {
            let mut add = |target: Option<ModPath>, line: usize| {
                if let Some(target) = target {
                    if target != source.module {
                        edges
                            .entry((source.module.clone(), target))
                            .or_default()
                            .insert(Place {
                                file: source.rel.clone(),
                                line,
                            });
                    }
                }
            };
            // Modules a `use` named, by the name the file knows them by.
            let mut aliases: BTreeMap<String, ModPath> = BTreeMap::new();
            for u in uses {
                let target = resolver.resolve(&u.scope, &u.segments, &BTreeMap::new());
                if let (Some(name), Some(t)) = (&u.name, &target) {
                    if let Some(abs) = absolute(&modules, &u.scope, &u.segments, &BTreeMap::new()) {
                        if modules.contains(&abs) {
                            aliases.insert(name.clone(), t.clone());
                        }
                    }
                }
                // A re-export is the module's namespace, not its code, unless the file uses
                // the name itself.
                let counts = !u.public
                    || u.name.is_none()
                    || u.name.as_ref().is_some_and(|n| used_idents.contains(n));
                if counts {
                    add(target, u.line);
                }
            }
            for w in written {
                add(resolver.resolve(&w.scope, &w.segments, &aliases), w.line);
            }
            for (line, doc, inner) in &source.docs {
                for link in doc_links(doc) {
                    let segments: Vec<String> = link.split("::").map(str::to_string).collect();
                    // Links resolve in the scope of the item they document; the file's
                    // module is that scope but for items in inline modules (rare in docs).
                    let target = resolver.resolve(&source.module, &segments, &aliases);
                    // A root's own documentation naming its children is its table of
                    // contents, like its `mod` lines, not a use of them.
                    let own_child = target.as_ref().is_some_and(|t| {
                        t.len() > source.module.len() && t.starts_with(&source.module)
                    });
                    if !(*inner && own_child) {
                        add(target, *line);
                    }
                }
            }
        }
        Ok(Graph { edges, modules })
    }

    /// Every level's graph and its cycles, with `allowed` edges left out of the cycles.
    fn report(&self, allowed: &[(&str, &str)]) -> Report {
        // Levels: every module that has children.
        let parents: BTreeSet<ModPath> = self
            .modules
            .iter()
            .filter(|m| !m.is_empty())
            .map(|m| m[..m.len() - 1].to_vec())
            .collect();
        let mut text = String::new();
        let mut cycles = Vec::new();
        let mut seen_allowed = BTreeSet::new();
        for level in &parents {
            // Edges between the nodes of this level, each with its places.
            let mut level_edges: BTreeMap<(String, String), BTreeSet<Place>> = BTreeMap::new();
            for ((from, to), places) in &self.edges {
                let (Some(a), Some(b)) = (node_at(level, from), node_at(level, to)) else {
                    continue;
                };
                if a != b {
                    level_edges
                        .entry((a, b))
                        .or_default()
                        .extend(places.iter().cloned());
                }
            }
            let kept: BTreeMap<&(String, String), &BTreeSet<Place>> = level_edges
                .iter()
                .filter(|(e, _)| {
                    let allow = allowed.iter().any(|(f, t)| *f == e.0 && *t == e.1);
                    if allow {
                        seen_allowed.insert((e.0.clone(), e.1.clone()));
                    }
                    !allow
                })
                .collect();
            let found = find_cycles(kept.keys().map(|e| (e.0.as_str(), e.1.as_str())));
            text += &format!(
                "level `{}`: {} edges between {} nodes, {} allowed, {} cycle(s)\n",
                name(level),
                level_edges.len(),
                self.modules
                    .iter()
                    .filter_map(|m| node_at(level, m))
                    .collect::<BTreeSet<_>>()
                    .len(),
                level_edges.len() - kept.len(),
                found.len()
            );
            for cycle in &found {
                let mut shown = format!("cycle in `{}`: {}", name(level), cycle.join(" → "));
                shown += &format!(" → {}\n", cycle[0]);
                for (i, from) in cycle.iter().enumerate() {
                    let to = &cycle[(i + 1) % cycle.len()];
                    let places = kept[&(from.clone(), to.clone())];
                    shown += &format!("  {from} → {to}: {}\n", list(places));
                }
                text += &shown;
                cycles.push(shown);
            }
            for ((from, to), places) in level_edges.iter().filter(|(e, _)| !kept.contains_key(e)) {
                text += &format!("  allowed: {from} → {to}: {}\n", list(places));
            }
            // The cycles the allowed edges close, so the report shows what is left to do.
            let all = find_cycles(level_edges.keys().map(|e| (e.0.as_str(), e.1.as_str())));
            for cycle in all.iter().filter(|c| !found.contains(c)) {
                text += &format!(
                    "  known cycle (allowed): {} → {}\n",
                    cycle.join(" → "),
                    cycle[0]
                );
            }
        }
        let stale = allowed
            .iter()
            .filter(|(f, t)| !seen_allowed.contains(&(f.to_string(), t.to_string())))
            .map(|(f, t)| (f.to_string(), t.to_string()))
            .collect();
        Report {
            text,
            cycles,
            stale,
        }
    }
}

/// At most a few places of an edge, and how many more.
fn list(places: &BTreeSet<Place>) -> String {
    let shown: Vec<String> = places
        .iter()
        .take(4)
        .map(|p| format!("{}:{}", p.file, p.line))
        .collect();
    let more = places.len().saturating_sub(4);
    if more > 0 {
        format!("{} (+{more} more)", shown.join(", "))
    } else {
        shown.join(", ")
    }
}

fn name(module: &[String]) -> String {
    if module.is_empty() {
        "crate".into()
    } else {
        module.join("::")
    }
}

/// The node a module is at `level`: the child of `level` it is or is inside, or the
/// level's own file (its `mod.rs`, or `lib.rs`), `level (root)`.
fn node_at(level: &[String], module: &[String]) -> Option<String> {
    if !module.starts_with(level) {
        return None;
    }
    if module.len() == level.len() {
        return Some(format!("{} (root)", name(level)));
    }
    Some(name(&module[..level.len() + 1]))
}

/// Cycles of a graph: for every edge inside a strongly connected component, the shortest
/// cycle through it; each cycle once, starting at its least node.
fn find_cycles<'a>(edges: impl Iterator<Item = (&'a str, &'a str)>) -> Vec<Vec<String>> {
    let mut next: BTreeMap<&str, BTreeSet<&str>> = BTreeMap::new();
    for (a, b) in edges {
        next.entry(a).or_default().insert(b);
        next.entry(b).or_default();
    }
    let mut cycles = BTreeSet::new();
    for (&a, outs) in &next {
        for &b in outs {
            // Shortest path b → a.
            let mut back: BTreeMap<&str, &str> = BTreeMap::new();
            let mut queue = VecDeque::from([b]);
            let mut reached = a == b;
            while let Some(n) = queue.pop_front() {
                if n == a {
                    reached = true;
                    break;
                }
                for &m in &next[n] {
                    if m != b && !back.contains_key(m) {
                        back.insert(m, n);
                        queue.push_back(m);
                    }
                }
            }
            if !reached {
                continue;
            }
            let mut path = vec![a];
            let mut n = a;
            while n != b {
                n = back[n];
                path.push(n);
            }
            // path is a, …, b backwards from a: the cycle is a → b → … → a.
            path.reverse();
            path.rotate_right(1);
            let least = (0..path.len()).min_by_key(|&i| path[i]).unwrap();
            path.rotate_left(least);
            cycles.insert(path.iter().map(|s| s.to_string()).collect::<Vec<_>>());
        }
    }
    cycles.into_iter().collect()
}

struct Resolver<'a> {
    modules: &'a BTreeSet<ModPath>,
    reexports: &'a BTreeMap<ModPath, BTreeMap<String, Vec<String>>>,
    /// Names a module's `use` brings in from another crate (`pub use crispen_marlin as
    /// marlin` at the root): a path through one leaves the crate, where Cargo keeps the
    /// order.
    foreign: &'a BTreeMap<ModPath, BTreeSet<String>>,
}

impl Resolver<'_> {
    /// The file module a path written in `scope` lands in, following re-exports; None
    /// when it names nothing of the crate (std, other crates, local items).
    fn resolve(
        &self,
        scope: &[String],
        segments: &[String],
        aliases: &BTreeMap<String, ModPath>,
    ) -> Option<ModPath> {
        let mut path = absolute(self.modules, scope, segments, aliases)?;
        for _ in 0..8 {
            // The deepest module on the path, then a re-export of the next name.
            let depth = (0..=path.len())
                .rev()
                .find(|&n| self.modules.contains(&path[..n].to_vec()))?;
            let module = path[..depth].to_vec();
            if path
                .get(depth)
                .is_some_and(|n| self.foreign.get(&module).is_some_and(|f| f.contains(n)))
            {
                return None;
            }
            match path
                .get(depth)
                .and_then(|n| self.reexports.get(&module)?.get(n))
            {
                Some(target) => {
                    let mut next = target.clone();
                    next.extend_from_slice(&path[depth + 1..]);
                    path = next;
                }
                None => return Some(module),
            }
        }
        None
    }
}

/// A path made absolute from the crate root, or None when its first segment is not the
/// crate's (std, another crate, a local name).
fn absolute(
    modules: &BTreeSet<ModPath>,
    scope: &[String],
    segments: &[String],
    aliases: &BTreeMap<String, ModPath>,
) -> Option<Vec<String>> {
    let first = segments.first()?;
    let (mut path, rest) = match first.as_str() {
        "crate" | "$crate" | "crispen" => (Vec::new(), &segments[1..]),
        "self" => (scope.to_vec(), &segments[1..]),
        "super" => {
            let mut path = scope.to_vec();
            let mut i = 0;
            while segments.get(i).is_some_and(|s| s == "super") {
                path.pop()?;
                i += 1;
            }
            (path, &segments[i..])
        }
        child => {
            let mut inside = scope.to_vec();
            inside.push(child.to_string());
            if modules.contains(&inside) {
                (inside, &segments[1..])
            } else {
                (aliases.get(child)?.clone(), &segments[1..])
            }
        }
    };
    path.extend(rest.iter().filter(|s| *s != "self").cloned());
    Some(path)
}

impl Source {
    /// The file's `use` statements (expanded), its other paths, and the identifiers it
    /// uses outside `use` statements.
    fn parse(&self) -> (Vec<Use>, Vec<Written>, BTreeSet<String>) {
        let t = &self.tokens;
        let mut uses = Vec::new();
        let mut written = Vec::new();
        let mut idents = BTreeSet::new();
        // Inline modules: (name, brace depth inside it).
        let mut inline: Vec<(String, usize)> = Vec::new();
        let mut depth = 0usize;
        let mut i = 0;
        let scope = |inline: &Vec<(String, usize)>| {
            let mut s = self.module.clone();
            s.extend(inline.iter().map(|(n, _)| n.clone()));
            s
        };
        while i < t.len() {
            if t[i].is('{') {
                depth += 1;
                i += 1;
                continue;
            }
            if t[i].is('}') {
                if inline.last().is_some_and(|(_, d)| *d == depth) {
                    inline.pop();
                }
                depth = depth.saturating_sub(1);
                i += 1;
                continue;
            }
            match t[i].ident() {
                Some("pub") if t.get(i + 1).is_some_and(|t| t.is('(')) => {
                    // `pub(in crate::a)` restricts visibility; it uses nothing.
                    i = (i + 1..t.len())
                        .find(|&k| t[k].is(')'))
                        .map_or(t.len(), |k| k + 1);
                    continue;
                }
                Some("mod") if i + 2 < t.len() && t[i + 2].is('{') => {
                    if let Some(name) = t[i + 1].ident() {
                        inline.push((name.to_string(), depth + 1));
                    }
                    i += 2;
                    continue;
                }
                Some("mod") => {
                    // `mod x;` declares a child; it is not a dependency.
                    i += 2;
                    continue;
                }
                Some("use") if i == 0 || !t[i - 1].is('.') => {
                    // `pub use`, or `pub(…) use` with any restriction inside.
                    let public = i > 0
                        && (t[i - 1].ident() == Some("pub")
                            || (t[i - 1].is(')')
                                && (0..i - 1)
                                    .rev()
                                    .find(|&k| t[k].is('('))
                                    .is_some_and(|k| k > 0 && t[k - 1].ident() == Some("pub"))));
                    let end = (i..t.len()).find(|&j| t[j].is(';')).unwrap_or(t.len());
                    let mut trees = Vec::new();
                    expand_use(&t[i + 1..end], Vec::new(), &mut trees);
                    for (segments, name, line) in trees {
                        uses.push(Use {
                            scope: scope(&inline),
                            segments,
                            name,
                            public,
                            line,
                        });
                    }
                    i = end + 1;
                    continue;
                }
                Some(_) => {
                    // A path: ident (:: ident)*, not a field or method after `.`.
                    let after_dot = i > 0 && t[i - 1].is('.');
                    let mut segments = vec![t[i].ident().unwrap().to_string()];
                    let mut line = t[i].line;
                    let mut j = i + 1;
                    while j + 1 < t.len() && t[j].tok == Tok::PathSep {
                        match t[j + 1].ident() {
                            Some(s) => {
                                segments.push(s.to_string());
                                line = t[j + 1].line;
                                j += 2;
                            }
                            None => break,
                        }
                    }
                    for s in &segments {
                        idents.insert(s.clone());
                    }
                    if segments.len() > 1 && !after_dot {
                        written.push(Written {
                            scope: scope(&inline),
                            segments,
                            line,
                        });
                    }
                    i = j;
                    continue;
                }
                None => {}
            }
            i += 1;
        }
        (uses, written, idents)
    }
}

/// Expands a use tree (the tokens between `use` and `;`) into full paths, each with the
/// name it binds (None for a glob) and the line of its last segment.
fn expand_use(
    t: &[Token],
    prefix: Vec<String>,
    out: &mut Vec<(Vec<String>, Option<String>, usize)>,
) {
    // Split the top level at commas (for the inside of braces).
    let mut start = 0;
    let mut depth = 0;
    let mut parts = Vec::new();
    for (k, tok) in t.iter().enumerate() {
        if tok.is('{') {
            depth += 1;
        } else if tok.is('}') {
            depth -= 1;
        } else if tok.is(',') && depth == 0 {
            parts.push(&t[start..k]);
            start = k + 1;
        }
    }
    parts.push(&t[start..]);
    for part in parts {
        let mut path = prefix.clone();
        let mut line = part.first().map_or(0, |t| t.line);
        let mut k = 0;
        let mut done = false;
        while k < part.len() {
            match &part[k].tok {
                Tok::Ident(s) if s == "as" => {
                    let name = part.get(k + 1).and_then(|t| t.ident()).map(str::to_string);
                    out.push((path.clone(), name.filter(|n| n != "_"), line));
                    done = true;
                    break;
                }
                Tok::Ident(s) => {
                    path.push(s.clone());
                    line = part[k].line;
                }
                Tok::PathSep => {}
                Tok::Punct('{') => {
                    let close =
                        part.len() - 1 - part.iter().rev().position(|t| t.is('}')).unwrap_or(0);
                    expand_use(&part[k + 1..close], path.clone(), out);
                    done = true;
                    break;
                }
                Tok::Punct('*') => {
                    out.push((path.clone(), None, line));
                    done = true;
                    break;
                }
                Tok::Punct(_) => {}
            }
            k += 1;
        }
        if !done && !path.is_empty() && path.len() > prefix.len() {
            // `a::b::{self}` binds `b`; otherwise the last segment.
            let name = match path.last().map(String::as_str) {
                Some("self") => {
                    path.pop();
                    path.last().cloned()
                }
                other => other.map(str::to_string),
            };
            out.push((path, name, line));
        }
    }
}

/// Paths of the crate named by intra-doc links in one doc line.
fn doc_links(doc: &str) -> Vec<String> {
    let mut links = Vec::new();
    let bytes = doc.as_bytes();
    let mut i = 0;
    while let Some(open) = doc[i..].find('[').map(|k| k + i) {
        let Some(close) = doc[open + 1..].find(']').map(|k| k + open + 1) else {
            break;
        };
        let inner = &doc[open + 1..close];
        let target = match bytes.get(close + 1) {
            Some(b'(') => doc[close + 2..]
                .find(')')
                .map(|k| &doc[close + 2..close + 2 + k]),
            Some(b':') => Some(doc[close + 2..].trim()),
            Some(b'[') => None,
            _ => Some(inner),
        };
        if let Some(target) = target {
            if let Some(path) = as_path(target) {
                links.push(path);
            }
        }
        i = close + 1;
    }
    links
}

/// A link target as a path (`struct@a::B`, `a::f()`, `m!` and backticks allowed), or None.
fn as_path(target: &str) -> Option<String> {
    let mut t = target.trim().trim_matches('`');
    if let Some((_, rest)) = t.split_once('@') {
        t = rest;
    }
    let t = t.trim_end_matches("()").trim_end_matches('!');
    let t = t.split('<').next()?;
    let ok = !t.is_empty()
        && t.split("::").all(|s| {
            !s.is_empty()
                && s.chars().all(|c| c.is_alphanumeric() || c == '_')
                && !s.starts_with(|c: char| c.is_ascii_digit())
        });
    ok.then(|| t.to_string())
}

fn walk(dir: &Path, files: &mut Vec<PathBuf>) -> Result<(), String> {
    let entries =
        std::fs::read_dir(dir).map_err(|e| format!("{}: cannot list: {e}", dir.display()))?;
    for entry in entries {
        let path = entry.map_err(|e| e.to_string())?.path();
        if path.is_dir() {
            walk(&path, files)?;
        } else if path.extension().is_some_and(|e| e == "rs") {
            files.push(path);
        }
    }
    Ok(())
}

/// `daemon/prepare/mod.rs` → daemon::prepare; `lib.rs` and `main.rs` → the root.
fn module_of(rel: &Path) -> ModPath {
    let mut parts: Vec<String> = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    let last = parts.pop().unwrap();
    let stem = last.trim_end_matches(".rs");
    if !(parts.is_empty() && (stem == "lib" || stem == "main")) && stem != "mod" {
        parts.push(stem.to_string());
    }
    parts
}

// ----------------------------------------------------------------------------- the lexer

/// Tokens of Rust text and its doc comments' lines (each with its line number).
type Lexed = (Vec<Token>, Vec<(usize, String, bool)>);

/// Tokens of Rust text (identifiers, `::`, punctuation) and its doc comments' lines;
/// comments, strings and character literals are skipped.
fn lex(text: &str) -> Result<Lexed, String> {
    let c: Vec<char> = text.chars().collect();
    let mut tokens = Vec::new();
    let mut docs = Vec::new();
    let mut line = 1;
    let mut i = 0;
    let count_lines = |from: usize, to: usize, line: &mut usize| {
        *line += c[from..to].iter().filter(|&&ch| ch == '\n').count();
    };
    while i < c.len() {
        let ch = c[i];
        let next = c.get(i + 1).copied();
        if ch == '\n' {
            line += 1;
            i += 1;
        } else if ch.is_whitespace() {
            i += 1;
        } else if ch == '/' && next == Some('/') {
            let end = (i..c.len()).find(|&k| c[k] == '\n').unwrap_or(c.len());
            let body: String = c[i + 2..end].iter().collect();
            let is_doc =
                (body.starts_with('/') && !body.starts_with("//")) || body.starts_with('!');
            if is_doc {
                docs.push((line, body[1..].to_string(), body.starts_with('!')));
            }
            i = end;
        } else if ch == '/' && next == Some('*') {
            let start = i;
            let mut nest = 0;
            while i < c.len() {
                if c[i] == '/' && c.get(i + 1) == Some(&'*') {
                    nest += 1;
                    i += 2;
                } else if c[i] == '*' && c.get(i + 1) == Some(&'/') {
                    nest -= 1;
                    i += 2;
                    if nest == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
            let body: String = c[start..i].iter().collect();
            if body.starts_with("/**") && !body.starts_with("/***") || body.starts_with("/*!") {
                let inner = body.starts_with("/*!");
                for (k, l) in body.lines().enumerate() {
                    docs.push((line + k, l.to_string(), inner));
                }
            }
            count_lines(start, i, &mut line);
        } else if ch == '"' {
            let start = i;
            i = skip_string(&c, i + 1)?;
            count_lines(start, i, &mut line);
        } else if ch == '\'' {
            // A character literal, or a lifetime / label.
            if next == Some('\\') {
                let end = (i + 2..c.len())
                    .find(|&k| c[k] == '\'')
                    .ok_or("open char")?;
                i = end + 1;
            } else if c.get(i + 2) == Some(&'\'') {
                i += 3;
            } else {
                i += 1;
            }
        } else if ch.is_alphabetic() || ch == '_' || ch == '$' {
            let start = i;
            i += 1;
            while i < c.len() && (c[i].is_alphanumeric() || c[i] == '_') {
                i += 1;
            }
            let word: String = c[start..i].iter().collect();
            let quote = c.get(i).copied();
            match (word.as_str(), quote) {
                ("r" | "br" | "cr", Some('#' | '"')) => {
                    let mut hashes = 0;
                    let mut k = i;
                    while c.get(k) == Some(&'#') {
                        hashes += 1;
                        k += 1;
                    }
                    if c.get(k) == Some(&'"') {
                        // A raw string: up to `"` and as many `#`.
                        let from = i;
                        k += 1;
                        loop {
                            if k >= c.len() {
                                return Err("open raw string".into());
                            }
                            if c[k] == '"' && (0..hashes).all(|h| c.get(k + 1 + h) == Some(&'#')) {
                                break;
                            }
                            k += 1;
                        }
                        i = k + 1 + hashes;
                        count_lines(from, i, &mut line);
                    } else {
                        // A raw identifier `r#name`.
                        tokens.push(Token {
                            tok: Tok::Punct('#'),
                            line,
                        });
                        i = k;
                    }
                }
                ("b" | "c", Some('"')) => {
                    let from = i;
                    i = skip_string(&c, i + 1)?;
                    count_lines(from, i, &mut line);
                }
                ("b", Some('\'')) => {
                    let end = if c.get(i + 1) == Some(&'\\') {
                        (i + 2..c.len())
                            .find(|&k| c[k] == '\'')
                            .ok_or("open byte")?
                    } else {
                        i + 2
                    };
                    i = end + 1;
                }
                _ => tokens.push(Token {
                    tok: Tok::Ident(word),
                    line,
                }),
            }
        } else if ch.is_ascii_digit() {
            while i < c.len() && (c[i].is_alphanumeric() || c[i] == '_' || c[i] == '.') {
                // `0..n`: stop before a range.
                if c[i] == '.' && c.get(i + 1) == Some(&'.') {
                    break;
                }
                i += 1;
            }
        } else if ch == ':' && next == Some(':') {
            tokens.push(Token {
                tok: Tok::PathSep,
                line,
            });
            i += 2;
        } else {
            tokens.push(Token {
                tok: Tok::Punct(ch),
                line,
            });
            i += 1;
        }
    }
    Ok((tokens, docs))
}

/// The index after the closing quote of a string whose body starts at `i`.
fn skip_string(c: &[char], mut i: usize) -> Result<usize, String> {
    while i < c.len() {
        match c[i] {
            '\\' => i += 2,
            '"' => return Ok(i + 1),
            _ => i += 1,
        }
    }
    Err("open string".into())
}
