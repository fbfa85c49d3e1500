//! The indexed triangle mesh and what reading one yields (its format, the cleaning report,
//! the memory limits, the errors): the definitions every reader, writer and the cleaner
//! share, apart from the root that dispatches to them.

use serde::Serialize;
use std::path::PathBuf;

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

    /// The mesh of the faces in `faces` alone, its vertices kept in their order here (one
    /// object of a 3MF's build, see [`LoadedMesh::objects`]).
    pub fn sub(&self, faces: std::ops::Range<usize>) -> Mesh {
        let faces = &self.faces[faces];
        let mut index = vec![u32::MAX; self.vertices.len()];
        for &i in faces.iter().flatten() {
            index[i as usize] = 0;
        }
        let mut vertices = Vec::new();
        for (slot, v) in index.iter_mut().zip(&self.vertices) {
            if *slot == 0 {
                *slot = vertices.len() as u32;
                vertices.push(*v);
            }
        }
        let faces = faces.iter().map(|f| f.map(|i| index[i as usize])).collect();
        Mesh { vertices, faces }
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
    /// The objects of a 3MF whose build places several (a plate of several models), each
    /// a run of `mesh`'s faces in build order; empty for a file of one object and for STL
    /// and OBJ, whose files hold one model.
    pub objects: Vec<MeshObject>,
}

/// One object of a 3MF's build: its name and its faces in the loaded mesh.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshObject {
    /// The object's `name`, or `object {id}` for one without.
    pub name: String,
    pub faces: std::ops::Range<usize>,
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

/// Parsed but not yet cleaned geometry. Indices are already validated.
pub struct RawMesh {
    pub vertices: Vec<[f64; 3]>,
    pub faces: Vec<[u32; 3]>,
    /// A 3MF's build items in order: each one's name and where its faces end.
    pub objects: Vec<(String, usize)>,
}
/// The (unnormalised) normal of triangle `f`: twice its area times its unit normal.
pub fn triangle_normal(vertices: &[[f64; 3]], f: [u32; 3]) -> [f64; 3] {
    let [a, b, c] = f.map(|i| vertices[i as usize]);
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ]
}
