//! The test meshes and reference outputs in `tests/data` (see its README), for the
//! integration tests and benchmarks. Large files are kept gzip-compressed in the
//! repository; each is decompressed once into the build folder and read from there as a
//! real file, as the daemon and the CLI read theirs.
#![allow(dead_code)] // each test binary uses its own part of this module

use crispen::mesh::Mesh;
use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};

/// A benchmark's runs: `CRISPEN_BENCH_RUNS`, or `default` (at least one).
pub fn bench_runs(default: usize) -> usize {
    std::env::var("CRISPEN_BENCH_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
        .max(1)
}

/// The middle of a benchmark's figures (the upper one of an even count).
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The median time of `runs` calls of `f`, seconds.
pub fn median_seconds<T>(runs: usize, mut f: impl FnMut() -> T) -> f64 {
    median(
        (0..runs)
            .map(|_| {
                let t = std::time::Instant::now();
                std::hint::black_box(f());
                t.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

/// Slices the test model `model` (Y up) `height_mm` tall for `machine` with PrusaSlicer,
/// unmodified and enhanced (the default strength), into `dir`: the two G-code files, in
/// that order, and the seconds both slicings took (the benchmarks' shared setup).
pub fn slice_plain_and_enhanced(
    dir: &Path,
    machine: &crispen::machine::Machine,
    model: &str,
    height_mm: f64,
) -> ([PathBuf; 2], f64) {
    use crispen::daemon::prepare::steps::{prepare_one, SliceRequest, Target};
    use crispen::enhance::Strength;
    let started = std::time::Instant::now();
    let paths = [("plain", Strength::Off), ("enhanced", Strength::Auto)].map(|(name, strength)| {
        let mut req = SliceRequest::new(self::model(&format!("{model}.obj")), height_mm);
        req.up = crispen::mesh::place::UpAxis::Y;
        req.strength = strength;
        let output = dir.join(format!("{model}-{name}-{height_mm}.gcode"));
        let target = Target {
            machine: machine.clone(),
            output: output.clone(),
            keep_mesh: None,
        };
        prepare_one(&req, target, &mut |_| {}).expect("PrusaSlicer slices the model");
        output
    });
    (paths, started.elapsed().as_secs_f64())
}

/// A pre-sliced file of `moves` short extruding moves stacked on one spot of the bed, all
/// within a square `within_mm` a side on the first layer (a purge or calibration pattern
/// does this; a file crafted so keeps a preview busy). It marks no kinds, so all of it is
/// drawn.
pub fn stacked_moves(moves: usize, within_mm: f64) -> String {
    let mut g = String::from("G90\nM83\nG1 Z0.2 F600\nG1 X100 Y100 F3000\n");
    // A zig-zag across the square, each stroke a little further along the other side.
    for i in 0..moves {
        let along = if i % 2 == 0 { within_mm } else { 0.0 };
        let across = within_mm * (i % 7) as f64 / 6.0;
        g += &format!(
            "G1 X{:.4} Y{:.4} E0.01 F1200\n",
            100.0 + along,
            100.0 + across
        );
    }
    g
}

pub fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data")
}

fn cache_dir() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join("crispen-test-data")
}

/// A model by its name (`spot.obj`, `bunny.obj`, `nefertiti.obj`, …) as a plain file.
pub fn model(name: &str) -> PathBuf {
    let plain = data_dir().join(name);
    if plain.exists() {
        return plain;
    }
    let packed = data_dir().join(format!("{name}.gz"));
    let cached = cache_dir().join(name);
    if is_newer_or_same(&cached, &packed) {
        return cached;
    }
    let mut bytes = Vec::new();
    flate2::read::GzDecoder::new(open(&packed))
        .read_to_end(&mut bytes)
        .unwrap_or_else(|e| panic!("decompressing {}: {e}", packed.display()));
    write_atomically(&cached, &bytes);
    cached
}

/// The job for `file` in a `crispen status --json` or `/api/v1/status` answer.
pub fn job_by_file<'a>(status: &'a serde_json::Value, file: &str) -> Option<&'a serde_json::Value> {
    status["jobs"]
        .as_array()?
        .iter()
        .find(|j| j["file"] == file)
}

/// The printer called `name` in a status answer; panics when there is none.
pub fn printer<'a>(status: &'a serde_json::Value, name: &str) -> &'a serde_json::Value {
    status["printers"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == name)
        .unwrap_or_else(|| panic!("no printer {name} in {status}"))
}

/// `reference.json`: the figures of the independent implementation.
pub fn reference_json() -> serde_json::Value {
    let path = data_dir().join("reference.json");
    serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap()
}

/// The bunny's bounding radius from `reference.json`.
pub fn bunny_radius() -> f64 {
    reference_json()["bunny"]["radius"].as_f64().unwrap()
}

/// The independent implementation's output for `bunny.obj` at λ2 = `lambda2` (10, 20 or
/// 40): bunny.obj's vertices, in order, plus the stored float32 displacements.
pub fn bunny_reference(bunny_vertices: &[[f64; 3]], lambda2: u32) -> Vec<[f64; 3]> {
    let path = data_dir().join(format!("bunny.lambda{lambda2}.displacement.f32.gz"));
    let mut bytes = Vec::new();
    flate2::read::GzDecoder::new(open(&path))
        .read_to_end(&mut bytes)
        .unwrap();
    assert_eq!(
        bytes.len(),
        bunny_vertices.len() * 12,
        "{} holds one x, y, z float32 triple per vertex",
        path.display()
    );
    bytes
        .chunks_exact(12)
        .zip(bunny_vertices)
        .map(|(d, v)| {
            std::array::from_fn(|k| {
                let c = f32::from_le_bytes(d[4 * k..4 * k + 4].try_into().unwrap());
                v[k] + f64::from(c)
            })
        })
        .collect()
}

/// `bunny.obj` as a binary STL triangle soup (every vertex repeated per face, as slicers
/// and CAD tools write it). Its coordinates are float32-exact, so the STL holds the same
/// geometry as the OBJ.
pub fn bunny_stl() -> PathBuf {
    let obj = model("bunny.obj");
    let stl = cache_dir().join("bunny.stl");
    if is_newer_or_same(&stl, &obj) {
        return stl;
    }
    let mesh = crispen::mesh::load(&obj).unwrap().mesh;
    let mut bytes = Vec::new();
    crispen::mesh::write_stl(&mut bytes, &mesh).unwrap();
    write_atomically(&stl, &bytes);
    stl
}

fn open(path: &Path) -> std::fs::File {
    std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn is_newer_or_same(made: &Path, source: &Path) -> bool {
    let mtime = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    matches!((mtime(made), mtime(source)), (Some(m), Some(s)) if m >= s)
}

/// Tests run in parallel threads and binaries: write under a unique name, then rename, so
/// no reader ever sees a half-written file.
fn write_atomically(path: &Path, bytes: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let mut tmp = tempfile::NamedTempFile::new_in(path.parent().unwrap()).unwrap();
    std::io::Write::write_all(&mut tmp, bytes).unwrap();
    tmp.persist(path).unwrap();
}

/// Splits every edge into `k` segments and every triangle into k² (k = 2 is the usual
/// midpoint 1→4 subdivision). Shared edges get shared vertices, so the result stays a
/// closed manifold mesh when the input is.
pub fn subdivide(mesh: &Mesh, k: usize) -> Mesh {
    let mut vertices = mesh.vertices.clone();
    let mut faces = Vec::with_capacity(mesh.faces.len() * k * k);
    let mut edge_start: HashMap<(u32, u32), u32> = HashMap::new();
    let lerp = |a: [f64; 3], b: [f64; 3], t: f64| -> [f64; 3] {
        std::array::from_fn(|c| a[c] + (b[c] - a[c]) * t)
    };
    let mut grid = vec![0u32; (k + 1) * (k + 1)];
    for f in &mesh.faces {
        let [a, b, c] = *f;
        // Point m of k on the edge u→v, shared with the neighbour across it.
        let mut edge_point = |u: u32, v: u32, m: usize, vertices: &mut Vec<[f64; 3]>| -> u32 {
            if m == 0 {
                return u;
            }
            if m == k {
                return v;
            }
            let (lo, hi, m_lo) = if u < v { (u, v, m) } else { (v, u, k - m) };
            let start = *edge_start.entry((lo, hi)).or_insert_with(|| {
                let start = vertices.len() as u32;
                for s in 1..k {
                    let p = lerp(
                        vertices[lo as usize],
                        vertices[hi as usize],
                        s as f64 / k as f64,
                    );
                    vertices.push(p);
                }
                start
            });
            start + (m_lo - 1) as u32
        };
        // Barycentric grid: point (i, j) = a + i/k (b − a) + j/k (c − a).
        for j in 0..=k {
            for i in 0..=(k - j) {
                let index = if j == 0 {
                    edge_point(a, b, i, &mut vertices)
                } else if i == 0 {
                    edge_point(a, c, j, &mut vertices)
                } else if i + j == k {
                    edge_point(b, c, j, &mut vertices)
                } else {
                    let (pa, pb, pc) = (
                        vertices[a as usize],
                        vertices[b as usize],
                        vertices[c as usize],
                    );
                    let (s, t) = (i as f64 / k as f64, j as f64 / k as f64);
                    vertices.push(std::array::from_fn(|d| {
                        pa[d] + s * (pb[d] - pa[d]) + t * (pc[d] - pa[d])
                    }));
                    vertices.len() as u32 - 1
                };
                grid[j * (k + 1) + i] = index;
            }
        }
        let g = |i: usize, j: usize| grid[j * (k + 1) + i];
        for j in 0..k {
            for i in 0..(k - j) {
                faces.push([g(i, j), g(i + 1, j), g(i, j + 1)]);
                if i + j + 1 < k {
                    faces.push([g(i + 1, j), g(i + 1, j + 1), g(i, j + 1)]);
                }
            }
        }
    }
    Mesh { vertices, faces }
}
pub mod bed;
pub mod camera;
pub mod daemon;
pub mod farm;
pub mod http;
pub mod plug;
pub mod postgres;
pub mod receiver;
pub mod relay;
pub mod spoolman;
