//! STL through `stl_io`, with the validation it does not do itself: a binary file's size
//! must be exactly 84 + 50·n bytes, counts are checked against the memory budget before
//! anything is allocated, and coordinates must be finite. STL is a triangle soup; the
//! caller welds it.

use super::{Limits, Mesh, MeshError, MeshFormat, RawMesh};
use std::io::{Cursor, Write};

pub(super) fn binary_size_matches(bytes: &[u8]) -> bool {
    if bytes.len() < 84 {
        return false;
    }
    let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as u64;
    84 + 50 * n == bytes.len() as u64
}

pub(super) fn parse_binary(
    bytes: &mut [u8],
    source_name: &str,
    limits: &Limits,
) -> Result<RawMesh, MeshError> {
    let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
    check_face_budget(n, source_name, limits)?;
    // The 80-byte header is free text that stl_io would mistake for ASCII when it starts
    // with "solid "; it carries nothing we use, so blank it.
    bytes[..80].fill(0);
    let mut cursor = Cursor::new(&*bytes);
    let reader = stl_io::create_stl_reader(&mut cursor)
        .map_err(|e| parse_error(source_name, "header", e))?;
    collect(reader, n, source_name, limits, |i| {
        format!("triangle {}", i + 1)
    })
}

pub(super) fn parse_ascii(
    bytes: &[u8],
    source_name: &str,
    limits: &Limits,
) -> Result<RawMesh, MeshError> {
    // stl_io insists on the first line starting with exactly "solid " (with a name);
    // exporters also write a bare "solid" or indent it. Normalise that first line.
    let start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(0);
    let rest = &bytes[start..];
    let first_line_end = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
    let mut normalised = Vec::with_capacity(rest.len() + 16);
    normalised.extend_from_slice(b"solid crispen\n");
    normalised.extend_from_slice(rest.get(first_line_end + 1..).unwrap_or(&[]));
    // A facet is at least 7 lines of ~10 bytes: bound the count before collecting.
    let estimate = normalised.len() / 70;
    let mut cursor = Cursor::new(normalised);
    let reader = stl_io::create_stl_reader(&mut cursor)
        .map_err(|e| parse_error(source_name, "first line", e))?;
    // A file cut short (a copy in progress, a failed download) ends without `endsolid`:
    // say so, rather than reporting the last, half-written facet as malformed.
    let complete = bytes
        .trim_ascii_end()
        .rsplit(|&b| b == b'\n')
        .next()
        .is_some_and(|last| last.trim_ascii_start().starts_with(b"endsolid"));
    collect(
        reader,
        estimate.min(limits.max_faces),
        source_name,
        limits,
        |i| format!("facet {}", i + 1),
    )
    .map_err(|e| match e {
        MeshError::Parse {
            source_name,
            format,
            location,
            ..
        } if !complete => MeshError::Parse {
            source_name,
            format,
            location,
            message: "the file ends here without `endsolid`: it is truncated (or still being \
                      copied)"
                .into(),
        },
        other => other,
    })
}

fn collect(
    reader: impl Iterator<Item = std::io::Result<stl_io::Triangle>>,
    capacity: usize,
    source_name: &str,
    limits: &Limits,
    location: impl Fn(usize) -> String,
) -> Result<RawMesh, MeshError> {
    let mut vertices = Vec::with_capacity(capacity * 3);
    let mut faces = Vec::with_capacity(capacity);
    for (i, triangle) in reader.enumerate() {
        let triangle = triangle.map_err(|e| parse_error(source_name, &location(i), e))?;
        check_face_budget(i + 1, source_name, limits)?;
        let base = vertices.len() as u32;
        for v in &triangle.vertices {
            if !v.0.iter().all(|c| c.is_finite()) {
                return Err(MeshError::NonFinite {
                    source_name: source_name.to_string(),
                    location: location(i),
                });
            }
            vertices.push(v.0.map(f64::from));
        }
        faces.push([base, base + 1, base + 2]);
    }
    Ok(RawMesh {
        vertices,
        faces,
        objects: Vec::new(),
    })
}

fn check_face_budget(n: usize, source_name: &str, limits: &Limits) -> Result<(), MeshError> {
    // A soup has three vertex records per triangle, but welding usually leaves about half
    // as many vertices as triangles, so the face cap is the binding one.
    if n > limits.max_faces {
        return Err(MeshError::TooLarge {
            source_name: source_name.to_string(),
            what: "triangles",
            count: n as u64,
            limit: limits.max_faces as u64,
        });
    }
    Ok(())
}

fn parse_error(source_name: &str, location: &str, e: std::io::Error) -> MeshError {
    let message = if e.kind() == std::io::ErrorKind::UnexpectedEof {
        format!("the file ends early ({e}); it is truncated")
    } else if e.to_string().contains("finite") {
        return MeshError::NonFinite {
            source_name: source_name.to_string(),
            location: location.to_string(),
        };
    } else {
        format!("invalid ASCII STL: {e}")
    };
    MeshError::Parse {
        source_name: source_name.to_string(),
        format: MeshFormat::Stl,
        location: location.to_string(),
        message,
    }
}

pub(super) fn write_binary(mut w: impl Write, mesh: &Mesh) -> std::io::Result<()> {
    let triangles = mesh.faces.iter().map(|f| {
        let [a, b, c] = f.map(|i| mesh.vertices[i as usize]);
        let n = super::triangle_normal(&mesh.vertices, *f);
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let n = if len > 0.0 {
            n.map(|x| x / len)
        } else {
            [0.0; 3]
        };
        let to32 = |p: [f64; 3]| stl_io::Vector::new(p.map(|x| x as f32));
        stl_io::Triangle {
            normal: to32(n),
            vertices: [to32(a), to32(b), to32(c)],
        }
    });
    if mesh.faces.len() > u32::MAX as usize {
        return Err(std::io::Error::other("too many triangles for binary STL"));
    }
    stl_io::write_stl(&mut w, triangles)
}
