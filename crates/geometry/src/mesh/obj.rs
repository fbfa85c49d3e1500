//! Wavefront OBJ: `v` and `f` records (polygons fan-triangulated; `i`, `i/t`, `i//n`,
//! `i/t/n` and negative, relative indices). Everything else (normals, texture
//! coordinates, groups, materials) does not affect the shape and is skipped. Output keeps
//! full f64 precision: Rust's `{}` for f64 prints the shortest string that round-trips.

use super::{Limits, Mesh, MeshError, MeshFormat, RawMesh};
use std::io::Write;

pub(super) fn parse(
    bytes: &[u8],
    source_name: &str,
    limits: &Limits,
) -> Result<RawMesh, MeshError> {
    let mut vertices: Vec<[f64; 3]> = Vec::new();
    let mut faces: Vec<[u32; 3]> = Vec::new();
    let mut polygon: Vec<u32> = Vec::new();
    for (line_index, raw_line) in bytes.split(|&b| b == b'\n').enumerate() {
        let line_no = line_index + 1;
        let err = |message: String| MeshError::Parse {
            source_name: source_name.to_string(),
            format: MeshFormat::Obj,
            location: format!("line {line_no}"),
            message,
        };
        let line = std::str::from_utf8(raw_line)
            .map_err(|_| err("not text (invalid UTF-8); this is not an OBJ file".into()))?;
        let line = line.split('#').next().unwrap_or("");
        let mut tokens = line.split_ascii_whitespace();
        match tokens.next() {
            Some("v") => {
                let mut v = [0.0f64; 3];
                for (k, c) in v.iter_mut().enumerate() {
                    let token = tokens
                        .next()
                        .ok_or_else(|| err(format!("vertex has {k} coordinates, needs 3")))?;
                    *c = token
                        .parse::<f64>()
                        .map_err(|_| err(format!("vertex coordinate {token:?} is not a number")))?;
                }
                if !v.iter().all(|c| c.is_finite()) {
                    return Err(MeshError::NonFinite {
                        source_name: source_name.to_string(),
                        location: format!("line {line_no} (vertex {})", vertices.len() + 1),
                    });
                }
                if vertices.len() >= limits.max_vertices {
                    return Err(MeshError::TooLarge {
                        source_name: source_name.to_string(),
                        what: "vertices",
                        count: vertices.len() as u64 + 1,
                        limit: limits.max_vertices as u64,
                    });
                }
                vertices.push(v);
            }
            Some("f") => {
                polygon.clear();
                for token in tokens {
                    let index_text = token.split('/').next().unwrap_or("");
                    let index: i64 = index_text
                        .parse()
                        .map_err(|_| err(format!("face vertex {token:?} is not an index")))?;
                    let n = vertices.len() as i64;
                    // OBJ indices are 1-based; negative ones count back from the last
                    // vertex defined so far.
                    let resolved = if index > 0 { index - 1 } else { n + index };
                    if index == 0 || resolved < 0 || resolved >= n {
                        return Err(err(format!(
                            "face refers to vertex {index}, but only {n} vertices are defined \
                             before this line"
                        )));
                    }
                    polygon.push(resolved as u32);
                }
                if polygon.len() < 3 {
                    return Err(err(format!(
                        "face has {} vertices, needs at least 3",
                        polygon.len()
                    )));
                }
                if faces.len() + polygon.len() - 2 > limits.max_faces {
                    return Err(MeshError::TooLarge {
                        source_name: source_name.to_string(),
                        what: "triangles",
                        count: (faces.len() + polygon.len() - 2) as u64,
                        limit: limits.max_faces as u64,
                    });
                }
                for k in 1..polygon.len() - 1 {
                    faces.push([polygon[0], polygon[k], polygon[k + 1]]);
                }
            }
            _ => {}
        }
    }
    Ok(RawMesh {
        vertices,
        faces,
        objects: Vec::new(),
    })
}

/// Writes `mesh` as OBJ: `v` lines at full precision, then 1-based `f` lines.
pub fn write_obj(mut w: impl Write, mesh: &Mesh) -> std::io::Result<()> {
    writeln!(
        w,
        "# written by crispen: {} vertices, {} faces",
        mesh.vertices.len(),
        mesh.faces.len()
    )?;
    for v in &mesh.vertices {
        writeln!(w, "v {} {} {}", v[0], v[1], v[2])?;
    }
    for f in &mesh.faces {
        writeln!(w, "f {} {} {}", f[0] + 1, f[1] + 1, f[2] + 1)?;
    }
    Ok(())
}
