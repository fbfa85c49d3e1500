//! Triangle meshes: reading STL / OBJ / 3MF, cleaning, writing STL / OBJ / 3MF, and placing a
//! mesh on a printer's bed ([`place`]).
//!
//! This is the geometry core's only I/O. Everything that reads a file is a thin wrapper
//! over a function taking `impl Read`, so tests feed bytes. The format is sniffed from the
//! content (the extension is only used to choose the *output* format). Every mesh that
//! comes in is cleaned as the enhancement spec asks (weld identical vertices, drop
//! degenerate faces and unreferenced vertices), so the enhancement engine can assume a
//! well-formed indexed mesh with finite coordinates.

mod clean;
mod indexed;
mod obj;
pub mod place;
mod stl;
mod threemf;
mod threemf_write;

pub use clean::clean;
pub use indexed::{triangle_normal, RawMesh};
pub use indexed::{CleanReport, Limits, LoadedMesh, Mesh, MeshError, MeshFormat, MeshObject};
pub use obj::write_obj;
pub use threemf_write::write_3mf;

use std::io::{Read, Write};
use std::path::Path;

/// Reads and cleans the mesh at `path`; the format is sniffed from the content.
pub fn load(path: &Path) -> Result<LoadedMesh, MeshError> {
    load_with_limits(path, &Limits::default())
}

/// [`load`] with an explicit memory budget.
pub(crate) fn load_with_limits(path: &Path, limits: &Limits) -> Result<LoadedMesh, MeshError> {
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
    let (names, mut ends): (Vec<String>, Vec<usize>) = raw.objects.into_iter().unzip();
    let (mesh, clean_report) = clean::clean_marked(raw.vertices, raw.faces, &mut ends);
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
    // Each object with faces left after cleaning is one; a build of one is the model.
    let mut start = 0;
    let mut objects = Vec::new();
    for (name, end) in names.into_iter().zip(ends) {
        if end > start {
            objects.push(MeshObject {
                name,
                faces: start..end,
            });
        }
        start = end;
    }
    if objects.len() < 2 {
        objects.clear();
    }
    Ok(LoadedMesh {
        mesh,
        format,
        clean: clean_report,
        objects,
    })
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
    crispen_fsutil::write_atomic_with(path, |file| {
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
