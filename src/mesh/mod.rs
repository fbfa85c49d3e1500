//! Triangle meshes: reading STL / OBJ / 3MF, cleaning, writing STL / OBJ, and placing a
//! mesh on a printer's bed ([`place`]).
//!
//! This is the geometry core's only I/O. Everything that reads a file is a thin wrapper
//! over a function taking `impl Read`, so tests feed bytes. The format is sniffed from the
//! content (the extension is only used to choose the *output* format). Every mesh that
//! comes in is cleaned as the enhancement spec asks (weld identical vertices, drop
//! degenerate faces and unreferenced vertices), so the enhancement engine can assume a
//! well-formed indexed mesh with finite coordinates.

mod clean;
mod obj;
pub mod place;
mod stl;
mod threemf;

pub use clean::clean;
pub use obj::write_obj;

use serde::Serialize;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

/// An indexed triangle mesh. Faces index into `vertices`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<[f64; 3]>,
    pub faces: Vec<[u32; 3]>,
}

impl Mesh {
    /// Axis-aligned bounding box (min, max); `None` for a mesh without vertices.
    pub fn bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        let first = *self.vertices.first()?;
        let mut lo = first;
        let mut hi = first;
        for v in &self.vertices {
            for k in 0..3 {
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
        Some((lo, hi))
    }
}

/// The file format a mesh was read from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum MeshFormat {
    #[serde(rename = "stl")]
    Stl,
    #[serde(rename = "obj")]
    Obj,
    #[serde(rename = "3mf")]
    ThreeMf,
}

impl std::fmt::Display for MeshFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            MeshFormat::Stl => "STL",
            MeshFormat::Obj => "OBJ",
            MeshFormat::ThreeMf => "3MF",
        })
    }
}

/// What cleaning changed (spec step 0).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct CleanReport {
    /// Vertex records merged into an earlier vertex with identical coordinates
    /// (for an STL triangle soup this is most of them).
    pub welded_vertices: usize,
    /// Faces dropped for a repeated vertex index or zero area.
    pub dropped_degenerate_faces: usize,
    /// Vertices no remaining face refers to.
    pub dropped_unreferenced_vertices: usize,
}

/// A mesh as read from a file, cleaned.
#[derive(Clone, Debug)]
pub struct LoadedMesh {
    pub mesh: Mesh,
    pub format: MeshFormat,
    pub clean: CleanReport,
}

/// The memory budget for reading: larger inputs are refused with [`MeshError::TooLarge`]
/// before they are materialised. The defaults keep a mesh at the cap enhanceable in
/// roughly 2 GiB (the sparse Cholesky factor dominates).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    pub max_vertices: usize,
    pub max_faces: usize,
    /// Size of the file as read.
    pub max_bytes: u64,
    /// Uncompressed XML of a 3MF file, all parts together (a small zip can inflate to
    /// gigabytes).
    pub max_xml_bytes: u64,
    /// Objects a 3MF file's build expands to through its components: nested components
    /// multiply, so a few kilobytes can otherwise name more instances than a computer can
    /// ever visit, even of empty objects.
    pub max_instances: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_vertices: 3_000_000,
            max_faces: 6_000_000,
            max_bytes: 1 << 30,
            max_xml_bytes: 1 << 30,
            max_instances: 100_000,
        }
    }
}

/// Why a mesh could not be read or written. Each names the file and, where the user can
/// act, says how.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("cannot read {source_name}: {source}")]
    Io {
        source_name: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{source_name}: the file is empty (hint: was the copy or upload interrupted?)")]
    Empty { source_name: String },
    #[error(
        "{source_name}: unknown mesh format: not a binary or ASCII STL, OBJ or 3MF file \
         (hint: export the model as STL, OBJ or 3MF)"
    )]
    UnknownFormat { source_name: String },
    #[error(
        "{source_name}: binary STL is truncated or corrupt: its header says {declared} \
         triangles ({expected_bytes} bytes) but the file has {actual_bytes} bytes \
         (hint: re-export or re-download the file)"
    )]
    TriangleCountMismatch {
        source_name: String,
        declared: u64,
        expected_bytes: u64,
        actual_bytes: u64,
    },
    #[error("{source_name}: {location}: {message}")]
    Parse {
        source_name: String,
        format: MeshFormat,
        location: String,
        message: String,
    },
    #[error(
        "{source_name}: {location} has a NaN or infinite coordinate \
         (hint: the exporter produced invalid geometry; repair the model)"
    )]
    NonFinite {
        source_name: String,
        location: String,
    },
    #[error("{source_name}: the mesh has no faces{detail}")]
    NoFaces { source_name: String, detail: String },
    #[error(
        "{source_name}: too large: {count} {what} exceeds the limit of {limit} \
         (hint: decimate the model; small prints do not need this much detail)"
    )]
    TooLarge {
        source_name: String,
        what: &'static str,
        count: u64,
        limit: u64,
    },
    #[error(
        "{}: cannot tell the output format from the extension (hint: use .stl or .obj)",
        path.display()
    )]
    UnsupportedOutput { path: PathBuf },
    #[error("cannot write {}: {source}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// Reads and cleans the mesh at `path`; the format is sniffed from the content.
pub fn load(path: &Path) -> Result<LoadedMesh, MeshError> {
    load_with_limits(path, &Limits::default())
}

/// [`load`] with an explicit memory budget.
pub fn load_with_limits(path: &Path, limits: &Limits) -> Result<LoadedMesh, MeshError> {
    let source_name = path.display().to_string();
    let file = std::fs::File::open(path).map_err(|source| MeshError::Io {
        source_name: source_name.clone(),
        source,
    })?;
    read_with_limits(file, &source_name, limits)
}

/// Reads and cleans a mesh from `reader`; `source_name` names it in errors.
pub fn read(reader: impl Read, source_name: &str) -> Result<LoadedMesh, MeshError> {
    read_with_limits(reader, source_name, &Limits::default())
}

/// [`read`] with an explicit memory budget.
pub fn read_with_limits(
    reader: impl Read,
    source_name: &str,
    limits: &Limits,
) -> Result<LoadedMesh, MeshError> {
    let mut bytes = Vec::new();
    // Read one byte past the budget so an over-long input is detected, not truncated.
    reader
        .take(limits.max_bytes.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|source| MeshError::Io {
            source_name: source_name.to_string(),
            source,
        })?;
    if bytes.len() as u64 > limits.max_bytes {
        return Err(MeshError::TooLarge {
            source_name: source_name.to_string(),
            what: "bytes",
            count: bytes.len() as u64,
            limit: limits.max_bytes,
        });
    }
    let (format, raw) = parse_bytes(bytes, source_name, limits)?;
    let (mesh, clean_report) = clean(raw.vertices, raw.faces);
    if mesh.faces.is_empty() {
        let detail = if clean_report.dropped_degenerate_faces > 0 {
            format!(
                " left after dropping {} degenerate (zero-area) faces",
                clean_report.dropped_degenerate_faces
            )
        } else {
            String::new()
        };
        return Err(MeshError::NoFaces {
            source_name: source_name.to_string(),
            detail,
        });
    }
    Ok(LoadedMesh {
        mesh,
        format,
        clean: clean_report,
    })
}

/// Parsed but not yet cleaned geometry. Indices are already validated.
pub(crate) struct RawMesh {
    pub vertices: Vec<[f64; 3]>,
    pub faces: Vec<[u32; 3]>,
}

fn parse_bytes(
    mut bytes: Vec<u8>,
    source_name: &str,
    limits: &Limits,
) -> Result<(MeshFormat, RawMesh), MeshError> {
    if bytes.iter().all(|b| b.is_ascii_whitespace()) {
        return Err(MeshError::Empty {
            source_name: source_name.to_string(),
        });
    }
    if bytes.starts_with(b"PK\x03\x04") {
        return threemf::parse(&bytes, source_name, limits).map(|m| (MeshFormat::ThreeMf, m));
    }
    // A binary STL is recognised by its size matching its triangle count, even when its
    // free-text header starts with "solid" (many exporters write that).
    if stl::binary_size_matches(&bytes) {
        return stl::parse_binary(&mut bytes, source_name, limits).map(|m| (MeshFormat::Stl, m));
    }
    let text_start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(0);
    let head = &bytes[text_start..bytes.len().min(text_start + 4096)];
    let looks_textual = !head.contains(&0);
    if looks_textual && head.len() >= 5 && head[..5].eq_ignore_ascii_case(b"solid") {
        return stl::parse_ascii(&bytes, source_name, limits).map(|m| (MeshFormat::Stl, m));
    }
    if looks_textual {
        let raw = obj::parse(&bytes, source_name, limits)?;
        if raw.vertices.is_empty() && raw.faces.is_empty() {
            return Err(MeshError::UnknownFormat {
                source_name: source_name.to_string(),
            });
        }
        return Ok((MeshFormat::Obj, raw));
    }
    if bytes.len() >= 84 {
        // Binary, not 3MF, size does not match: a damaged binary STL is by far the most
        // likely story; say so with the numbers.
        let declared = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as u64;
        return Err(MeshError::TriangleCountMismatch {
            source_name: source_name.to_string(),
            declared,
            expected_bytes: 84 + 50 * declared,
            actual_bytes: bytes.len() as u64,
        });
    }
    Err(MeshError::UnknownFormat {
        source_name: source_name.to_string(),
    })
}

/// Writes `mesh` to `path`, as binary STL or OBJ by the extension. The file is written
/// to a temporary name next to it and renamed, so an existing file is never left half
/// overwritten.
pub fn save(path: &Path, mesh: &Mesh) -> Result<(), MeshError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    let write: fn(&mut dyn Write, &Mesh) -> std::io::Result<()> = match ext.as_deref() {
        Some("stl") => |w, m| write_stl(w, m),
        Some("obj") => |w, m| write_obj(w, m),
        _ => {
            return Err(MeshError::UnsupportedOutput {
                path: path.to_path_buf(),
            })
        }
    };
    let write_err = |source| MeshError::Write {
        path: path.to_path_buf(),
        source,
    };
    crate::fsutil::write_atomic_with(path, |file| {
        let mut w = std::io::BufWriter::new(file);
        write(&mut w, mesh)?;
        w.flush()
    })
    .map_err(|e| write_err(e.into()))
}

/// Writes `mesh` as binary STL (f32 coordinates, per-face normals).
pub fn write_stl(w: impl Write, mesh: &Mesh) -> std::io::Result<()> {
    stl::write_binary(w, mesh)
}

/// The (unnormalised) normal of triangle `f`: twice its area times its unit normal.
pub(crate) fn triangle_normal(vertices: &[[f64; 3]], f: [u32; 3]) -> [f64; 3] {
    let [a, b, c] = f.map(|i| vertices[i as usize]);
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ]
}
