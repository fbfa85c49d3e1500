//! The test meshes and reference outputs in `tests/data` (see its README), for the
//! integration tests and benchmarks. Large files are kept gzip-compressed in the
//! repository; each is decompressed once into the build folder and read from there as a
//! real file, as the daemon and the CLI read theirs.
#![allow(dead_code)] // each test binary uses its own part of this module

use std::io::Read;
use std::path::{Path, PathBuf};

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
