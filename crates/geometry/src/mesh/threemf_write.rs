//! Writing 3MF: a plate of named objects in one file, as a folder of models dropped as one
//! job is kept (each model an object of its build, at its own coordinates, in millimetres).
//! Coordinates keep full f64 precision (Rust's `{}` prints the shortest string that reads
//! back to the same number), so reading the file gives back the meshes exactly.

use super::Mesh;
use std::io::{Seek, Write};

/// The package's parts other than the model: its content types and its relationship to
/// the model (3MF core specification, chapter 2), so slicers open the file too.
const CONTENT_TYPES: &str = r#"<?xml version="1.0" encoding="UTF-8"?>
<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types"><Default Extension="rels" ContentType="application/vnd.openxmlformats-package.relationships+xml"/><Default Extension="model" ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/></Types>"#;
const RELS: &str = r#"<?xml version="1.0" encoding="UTF-8"?>
<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships"><Relationship Target="/3D/3dmodel.model" Id="rel0" Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/></Relationships>"#;

/// Writes `objects` (each a name and its mesh) as one 3MF whose build places each once,
/// in order, untransformed. Streams: the model is never held whole in memory.
pub fn write_3mf<W: Write + Seek>(w: W, objects: &[(&str, &Mesh)]) -> std::io::Result<W> {
    let mut zip = zip::ZipWriter::new(w);
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    zip.start_file("[Content_Types].xml", options)?;
    zip.write_all(CONTENT_TYPES.as_bytes())?;
    zip.start_file("_rels/.rels", options)?;
    zip.write_all(RELS.as_bytes())?;
    zip.start_file("3D/3dmodel.model", options)?;
    {
        let mut m = std::io::BufWriter::new(&mut zip);
        m.write_all(
            b"<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<model unit=\"millimeter\" xml:lang=\"en-US\" \
              xmlns=\"http://schemas.microsoft.com/3dmanufacturing/core/2015/02\"><resources>",
        )?;
        for (i, (name, mesh)) in objects.iter().enumerate() {
            let name = quick_xml::escape::escape(*name);
            write!(
                m,
                "<object id=\"{}\" name=\"{name}\" type=\"model\"><mesh><vertices>",
                i + 1
            )?;
            for v in &mesh.vertices {
                write!(m, "<vertex x=\"{}\" y=\"{}\" z=\"{}\"/>", v[0], v[1], v[2])?;
            }
            m.write_all(b"</vertices><triangles>")?;
            for f in &mesh.faces {
                write!(
                    m,
                    "<triangle v1=\"{}\" v2=\"{}\" v3=\"{}\"/>",
                    f[0], f[1], f[2]
                )?;
            }
            m.write_all(b"</triangles></mesh></object>")?;
        }
        m.write_all(b"</resources><build>")?;
        for i in 0..objects.len() {
            write!(m, "<item objectid=\"{}\"/>", i + 1)?;
        }
        m.write_all(b"</build></model>")?;
        m.flush()?;
    }
    zip.finish().map_err(std::io::Error::other)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tetra(at: f64) -> Mesh {
        Mesh {
            vertices: vec![
                [at, 0.0, 0.0],
                [at + 1.0, 0.0, 0.0],
                [at, 1.0 / 3.0, 0.0],
                [at, 0.0, 0.1 + 0.2],
            ],
            faces: vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]],
        }
    }

    #[test]
    fn a_plate_written_reads_back_object_by_object_exactly() {
        let (a, b) = (tetra(0.0), tetra(5.0));
        let bytes = write_3mf(
            std::io::Cursor::new(Vec::new()),
            &[("gear & <nut>", &a), ("b", &b)],
        )
        .unwrap()
        .into_inner();
        let loaded = crate::mesh::read(&bytes[..], "plate.3mf").unwrap();
        assert_eq!(loaded.format, crate::mesh::MeshFormat::ThreeMf);
        let names: Vec<&str> = loaded.objects.iter().map(|o| o.name.as_str()).collect();
        assert_eq!(names, ["gear & <nut>", "b"]);
        for (object, mesh) in loaded.objects.iter().zip([&a, &b]) {
            let sub = loaded.mesh.sub(object.faces.clone());
            assert_eq!(&sub.vertices, &mesh.vertices, "no coordinate rounded");
            assert_eq!(&sub.faces, &mesh.faces);
        }
    }
}
