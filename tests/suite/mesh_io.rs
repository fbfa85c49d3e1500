//! Mesh readers and writers fed with bytes: every supported form, every kind of bad
//! input the issue lists (each must be a clear, typed error naming the source, never a
//! panic), and round trips through the writers.

use crispen::mesh::{self, Limits, Mesh, MeshError, MeshFormat};
use rand::{Rng, SeedableRng};
use std::io::{Cursor, Write};
use std::path::Path;

fn read(bytes: &[u8]) -> Result<mesh::LoadedMesh, MeshError> {
    mesh::read(Cursor::new(bytes), "test-input")
}

fn tetrahedron() -> Mesh {
    Mesh {
        vertices: vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ],
        faces: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    }
}

fn binary_stl(mesh: &Mesh, header: &[u8]) -> Vec<u8> {
    let mut bytes = Vec::new();
    mesh::write_stl(&mut bytes, mesh).unwrap();
    bytes[..header.len()].copy_from_slice(header);
    bytes
}

const ASCII_STL: &str = "  solid\n\
  facet normal 0 0 -1\n outer loop\n  vertex 0 0 0\n  vertex 0 1 0\n  vertex 1 0 0\n endloop\n endfacet\n\
  facet normal 0 -1 0\n outer loop\n  vertex 0 0 0\n  vertex 1 0 0\n  vertex 0 0 1\n endloop\n endfacet\n\
endsolid\n";

#[test]
fn binary_stl_is_read_and_welded_even_with_a_solid_header() {
    let bytes = binary_stl(&tetrahedron(), b"solid tetrahedron exported by a CAD tool");
    let loaded = read(&bytes).unwrap();
    assert_eq!(loaded.format, MeshFormat::Stl);
    assert_eq!(loaded.mesh.faces.len(), 4);
    assert_eq!(loaded.mesh.vertices.len(), 4);
    assert_eq!(loaded.clean.welded_vertices, 8);
}

#[test]
fn ascii_stl_is_read_with_a_bare_indented_solid_line() {
    let loaded = read(ASCII_STL.as_bytes()).unwrap();
    assert_eq!(loaded.format, MeshFormat::Stl);
    assert_eq!(loaded.mesh.faces.len(), 2);
    assert_eq!(loaded.mesh.vertices.len(), 4);
    assert_eq!(loaded.clean.welded_vertices, 2);
}

#[test]
fn truncated_and_mismatched_binary_stl_are_refused() {
    let bytes = binary_stl(&tetrahedron(), b"");
    for len in [bytes.len() - 1, bytes.len() - 50, 100] {
        match read(&bytes[..len]) {
            Err(e @ MeshError::TriangleCountMismatch { declared: 4, .. }) => {
                let text = e.to_string();
                assert!(
                    text.contains("test-input") && text.contains("truncated"),
                    "{text}"
                );
            }
            other => panic!("{len} bytes: {other:?}"),
        }
    }
    let mut longer = bytes.clone();
    longer.extend_from_slice(&[0u8; 7]);
    assert!(matches!(
        read(&longer),
        Err(MeshError::TriangleCountMismatch { .. })
    ));
    // A header claiming billions of triangles must not make us allocate for them.
    let mut huge = bytes.clone();
    huge[80..84].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(
        read(&huge),
        Err(MeshError::TriangleCountMismatch { .. })
    ));
}

#[test]
fn truncated_ascii_stl_is_refused() {
    let cut = &ASCII_STL[..ASCII_STL.rfind(" endloop").unwrap()];
    match read(cut.as_bytes()) {
        Err(e @ MeshError::Parse { .. }) => {
            let text = e.to_string();
            assert!(
                text.contains("facet 2") && text.contains("truncated"),
                "{text}"
            );
        }
        other => panic!("{other:?}"),
    }
    // Cut in the middle of a vertex line, as a copy in progress leaves it.
    let mid_line = &ASCII_STL[..ASCII_STL.rfind("vertex").unwrap() + 10];
    let text = read(mid_line.as_bytes()).unwrap_err().to_string();
    assert!(text.contains("truncated"), "{text}");
    // A complete file with a bad number is malformed, not truncated.
    let garbled = ASCII_STL.replace("vertex 0 1 0", "vertex 0 one 0");
    match read(garbled.as_bytes()) {
        Err(e @ MeshError::Parse { .. }) => {
            assert!(!e.to_string().contains("truncated"), "{e}")
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn non_finite_coordinates_are_refused_in_every_format() {
    let mut nan_stl = tetrahedron();
    nan_stl.vertices[3][1] = f64::NAN;
    match read(&binary_stl(&nan_stl, b"")) {
        Err(e @ MeshError::NonFinite { .. }) => {
            assert!(e.to_string().contains("triangle 2"), "{e}")
        }
        other => panic!("{other:?}"),
    }
    let inf_ascii = ASCII_STL.replace("vertex 0 0 1", "vertex inf 0 1");
    assert!(matches!(
        read(inf_ascii.as_bytes()),
        Err(MeshError::NonFinite { .. })
    ));
    match read(b"v 0 0 0\nv 1 0 0\nv 0 NaN 0\nf 1 2 3\n") {
        Err(e @ MeshError::NonFinite { .. }) => assert!(e.to_string().contains("line 3"), "{e}"),
        other => panic!("{other:?}"),
    }
    let model = model_xml(
        r#"<vertex x="0" y="0" z="0"/><vertex x="1" y="0" z="0"/><vertex x="0" y="1e999" z="0"/>"#,
        r#"<triangle v1="0" v2="1" v3="2"/>"#,
        "",
    );
    assert!(matches!(
        read(&three_mf(&[("3D/3dmodel.model", &model)])),
        Err(MeshError::NonFinite { .. })
    ));
}

#[test]
fn empty_faceless_and_unknown_inputs_are_refused() {
    assert!(matches!(read(b""), Err(MeshError::Empty { .. })));
    assert!(matches!(read(b"  \n\t\n"), Err(MeshError::Empty { .. })));
    assert!(matches!(
        read(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
        Err(MeshError::NoFaces { .. })
    ));
    match read(b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n") {
        Err(e @ MeshError::NoFaces { .. }) => assert!(e.to_string().contains("degenerate"), "{e}"),
        other => panic!("{other:?}"),
    }
    assert!(matches!(
        read(b"solid x\nendsolid x\n"),
        Err(MeshError::NoFaces { .. })
    ));
    assert!(matches!(
        read(b"hello, this is a text file\n"),
        Err(MeshError::UnknownFormat { .. })
    ));
    assert!(matches!(
        read(&[0u8, 159, 146, 150, 7, 1, 2]),
        Err(MeshError::UnknownFormat { .. })
    ));
    let e = read(b"").unwrap_err().to_string();
    assert!(e.contains("test-input") && e.contains("empty"), "{e}");
}

#[test]
fn obj_polygons_index_forms_and_order() {
    let text = "# a quad and a triangle with every index form\n\
                o thing\nv 0 0 0\nv 1 0 0 1.0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n\
                v 0.5 0.5 1 0.2 0.3 0.4\n\
                f 1/1/1 2/1/1 3//1 4\n\
                usemtl red\n\
                f -5 -4 -1 # relative indices\n";
    let loaded = read(text.as_bytes()).unwrap();
    assert_eq!(loaded.format, MeshFormat::Obj);
    assert_eq!(loaded.mesh.vertices[1], [1.0, 0.0, 0.0]);
    assert_eq!(loaded.mesh.vertices.len(), 5);
    assert_eq!(loaded.mesh.faces, vec![[0, 1, 2], [0, 2, 3], [0, 1, 4]]);
}

#[test]
fn obj_cleaning_keeps_survivor_order() {
    // Vertex 2 (1-based) is unused and vertex 5 duplicates vertex 1.
    let text = "v 0 0 0\nv 9 9 9\nv 1 0 0\nv 0 1 0\nv 0 0 0\nv 0 0 1\nf 5 3 4\nf 1 3 6\n";
    let loaded = read(text.as_bytes()).unwrap();
    assert_eq!(
        loaded.mesh.vertices,
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0]
        ]
    );
    assert_eq!(loaded.mesh.faces, vec![[0, 1, 2], [0, 1, 3]]);
    assert_eq!(loaded.clean.welded_vertices, 1);
    assert_eq!(loaded.clean.dropped_unreferenced_vertices, 1);
}

#[test]
fn obj_errors_name_the_line() {
    let cases: [(&str, &str); 5] = [
        ("v 0 0 0\nv 1 0 0\nf 1 2 3\n", "line 3"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n", "line 4"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n", "line 4"),
        ("v 0 0\n", "line 1"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", "line 4"),
    ];
    for (text, line) in cases {
        match read(text.as_bytes()) {
            Err(e @ MeshError::Parse { .. }) => {
                assert!(e.to_string().contains(line), "{text:?}: {e}")
            }
            other => panic!("{text:?}: {other:?}"),
        }
    }
}

#[test]
fn inputs_over_the_memory_budget_are_refused() {
    let tiny = Limits {
        max_vertices: 3,
        max_faces: 3,
        max_bytes: 1 << 20,
        ..Limits::default()
    };
    let too_large = |bytes: &[u8]| {
        matches!(
            mesh::read_with_limits(Cursor::new(bytes), "big", &tiny),
            Err(MeshError::TooLarge { .. })
        )
    };
    assert!(too_large(&binary_stl(&tetrahedron(), b"")));
    let mut obj = Vec::new();
    mesh::write_obj(&mut obj, &tetrahedron()).unwrap();
    assert!(too_large(&obj));
    let model = model_xml(
        r#"<vertex x="0" y="0" z="0"/><vertex x="1" y="0" z="0"/><vertex x="0" y="1" z="0"/><vertex x="0" y="0" z="1"/>"#,
        r#"<triangle v1="0" v2="2" v3="1"/>"#,
        "",
    );
    assert!(too_large(&three_mf(&[("3D/3dmodel.model", &model)])));
    let few_bytes = Limits {
        max_bytes: 100,
        ..Limits::default()
    };
    let e = mesh::read_with_limits(Cursor::new(&obj), "big", &few_bytes).unwrap_err();
    assert!(
        matches!(e, MeshError::TooLarge { what: "bytes", .. }),
        "{e}"
    );
    assert!(e.to_string().contains("hint"));
}

/// A 3MF file of a few kilobytes whose nested components name 10^10 instances of an
/// empty object: no vertex or face limit is ever reached, so only a limit on the
/// instances stops it (it once kept a preparation busy for days).
#[test]
fn three_mf_component_bomb_is_refused_quickly() {
    let mut objects = String::new();
    for id in 2..=10 {
        let components: String = (0..10)
            .map(|_| format!(r#"<component objectid="{}"/>"#, id + 1))
            .collect();
        objects += &format!(
            r#"<object id="{id}" type="model"><components>{components}</components></object>"#
        );
    }
    objects += r#"<object id="11" type="model"><mesh><vertices></vertices><triangles></triangles></mesh></object>"#;
    let top: String = (0..10).map(|_| r#"<component objectid="2"/>"#).collect();
    let model = format!(
        r#"<?xml version="1.0" encoding="UTF-8"?>
<model unit="millimeter" xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02">
 <resources><object id="1" type="model"><components>{top}</components></object>{objects}</resources>
 <build><item objectid="1"/></build>
</model>"#
    );
    let file = three_mf(&[("3D/3dmodel.model", &model)]);
    assert!(file.len() < 8 * 1024, "{} bytes", file.len());
    let e = read(&file).unwrap_err();
    assert!(
        matches!(e, MeshError::TooLarge { what, .. } if what.contains("instances")),
        "{e}"
    );
    assert!(e.to_string().contains("hint"), "{e}");
}

/// The uncompressed XML of all parts together has a limit of its own.
#[test]
fn three_mf_xml_over_its_limit_is_refused() {
    let model = model_xml(TETRA_VERTICES, TETRA_TRIANGLES, &" ".repeat(5000));
    let file = three_mf(&[("3D/3dmodel.model", &model)]);
    let limits = Limits {
        max_xml_bytes: 4096,
        ..Limits::default()
    };
    let e = mesh::read_with_limits(Cursor::new(&file), "big.3mf", &limits).unwrap_err();
    assert!(
        matches!(e, MeshError::TooLarge { what, limit: 4096, .. } if what.contains("XML")),
        "{e}"
    );
    mesh::read_with_limits(Cursor::new(&file), "big.3mf", &Limits::default()).unwrap();
}

fn model_xml(vertices: &str, triangles: &str, extra_objects: &str) -> String {
    format!(
        r#"<?xml version="1.0" encoding="UTF-8"?>
<model unit="millimeter" xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02">
 <resources>
  <object id="1" type="model"><mesh><vertices>{vertices}</vertices><triangles>{triangles}</triangles></mesh></object>
  {extra_objects}
 </resources>
 <build><item objectid="1"/></build>
</model>"#
    )
}

fn three_mf(parts: &[(&str, &str)]) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default();
    zip.start_file("[Content_Types].xml", options).unwrap();
    zip.write_all(b"<?xml version=\"1.0\"?><Types/>").unwrap();
    for (name, text) in parts {
        zip.start_file(*name, options).unwrap();
        zip.write_all(text.as_bytes()).unwrap();
    }
    zip.finish().unwrap().into_inner()
}

const TETRA_VERTICES: &str = r#"<vertex x="0" y="0" z="0"/><vertex x="1" y="0" z="0"/><vertex x="0" y="1" z="0"/><vertex x="0" y="0" z="1"/>"#;
const TETRA_TRIANGLES: &str = r#"<triangle v1="0" v2="2" v3="1"/><triangle v1="0" v2="1" v3="3"/><triangle v1="0" v2="3" v3="2"/><triangle v1="1" v2="2" v3="3"/>"#;

#[test]
fn three_mf_applies_build_and_component_transforms_and_units() {
    let plain = read(&three_mf(&[(
        "3D/3dmodel.model",
        &model_xml(TETRA_VERTICES, TETRA_TRIANGLES, ""),
    )]))
    .unwrap();
    assert_eq!(plain.format, MeshFormat::ThreeMf);
    assert_eq!(plain.mesh, tetrahedron());

    // PrusaSlicer / Bambu style: the build places an assembly whose component lives in
    // another part, in centimetres, translated and scaled twice.
    let root = r#"<?xml version="1.0" encoding="UTF-8"?>
<model unit="centimeter" xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02" xmlns:p="http://schemas.microsoft.com/3dmanufacturing/production/1515/06">
 <resources>
  <object id="7" type="model"><components><component p:path="/3D/Objects/part.model" objectid="3" transform="2 0 0 0 2 0 0 0 2 1 0 0"/></components></object>
 </resources>
 <build><item objectid="7" transform="1 0 0 0 1 0 0 0 1 0 0 5"/></build>
</model>"#;
    let part = format!(
        r#"<?xml version="1.0"?><model unit="centimeter" xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02"><resources>
<object id="3"><mesh><vertices>{TETRA_VERTICES}</vertices><triangles>{TETRA_TRIANGLES}</triangles></mesh></object></resources></model>"#
    );
    let loaded = read(&three_mf(&[
        ("3D/3dmodel.model", root),
        ("3D/Objects/part.model", &part),
    ]))
    .unwrap();
    // (p·2 + (1,0,0) + (0,0,5)) in cm → mm.
    let expected: Vec<[f64; 3]> = tetrahedron()
        .vertices
        .iter()
        .map(|v| {
            [
                (2.0 * v[0] + 1.0) * 10.0,
                2.0 * v[1] * 10.0,
                (2.0 * v[2] + 5.0) * 10.0,
            ]
        })
        .collect();
    assert_eq!(loaded.mesh.vertices, expected);
    assert_eq!(loaded.mesh.faces, tetrahedron().faces);
}

#[test]
fn three_mf_without_build_takes_each_top_level_object_once() {
    // Object 2 places object 1 (shifted up by 5); with no <build>, only 2 is printed, not
    // 1 as well.
    let model = r#"<?xml version="1.0"?>
<model unit="millimeter" xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02">
 <resources>
  <object id="1"><mesh><vertices>VERTICES</vertices><triangles>TRIANGLES</triangles></mesh></object>
  <object id="2"><components><component objectid="1" transform="1 0 0 0 1 0 0 0 1 0 0 5"/></components></object>
 </resources>
</model>"#
        .replace("VERTICES", TETRA_VERTICES)
        .replace("TRIANGLES", TETRA_TRIANGLES);
    let loaded = read(&three_mf(&[("3D/3dmodel.model", &model)])).unwrap();
    assert_eq!(loaded.mesh.faces, tetrahedron().faces);
    let shifted: Vec<[f64; 3]> = tetrahedron()
        .vertices
        .iter()
        .map(|v| [v[0], v[1], v[2] + 5.0])
        .collect();
    assert_eq!(loaded.mesh.vertices, shifted);
}

#[test]
fn broken_three_mf_is_refused() {
    // A zip without a model part.
    let e = read(&three_mf(&[("readme.txt", "hi")])).unwrap_err();
    assert!(
        matches!(
            e,
            MeshError::Parse {
                format: MeshFormat::ThreeMf,
                ..
            }
        ),
        "{e}"
    );
    // Malformed XML, and a triangle pointing past the vertices.
    let e = read(&three_mf(&[(
        "3D/3dmodel.model",
        "<model><resources><object id=\"1\"><mesh><vertices><vertex x=",
    )]))
    .unwrap_err();
    assert!(matches!(e, MeshError::Parse { .. }), "{e}");
    let model = model_xml(TETRA_VERTICES, r#"<triangle v1="0" v2="1" v3="9"/>"#, "");
    let e = read(&three_mf(&[("3D/3dmodel.model", &model)])).unwrap_err();
    assert!(e.to_string().contains("vertex 9"), "{e}");
    // A build item referring to a missing object.
    let model = model_xml(TETRA_VERTICES, TETRA_TRIANGLES, "")
        .replace(r#"<item objectid="1"/>"#, r#"<item objectid="2"/>"#);
    assert!(read(&three_mf(&[("3D/3dmodel.model", &model)])).is_err());
    // A truncated zip.
    let bytes = three_mf(&[(
        "3D/3dmodel.model",
        &model_xml(TETRA_VERTICES, TETRA_TRIANGLES, ""),
    )]);
    assert!(read(&bytes[..bytes.len() / 2]).is_err());
}

#[test]
fn writers_round_trip() {
    let mut m = tetrahedron();
    m.vertices[3] = [0.1, 1.0 / 3.0, std::f64::consts::PI];
    let mut obj = Vec::new();
    mesh::write_obj(&mut obj, &m).unwrap();
    assert_eq!(
        read(&obj).unwrap().mesh,
        m,
        "OBJ keeps full f64 precision and order"
    );

    let mut stl = Vec::new();
    mesh::write_stl(&mut stl, &m).unwrap();
    assert_eq!(stl.len(), 84 + 50 * 4);
    let back = read(&stl).unwrap().mesh;
    assert_eq!(back.faces.len(), 4);
    for v in &back.vertices {
        assert!(m
            .vertices
            .iter()
            .any(|w| (0..3).all(|k| (v[k] - w[k]).abs() < 1e-6)));
    }
}

#[test]
fn save_picks_the_format_by_extension_and_never_half_writes() {
    let dir = tempfile::tempdir().unwrap();
    let m = tetrahedron();
    for (name, format) in [("a.obj", MeshFormat::Obj), ("b.STL", MeshFormat::Stl)] {
        let path = dir.path().join(name);
        mesh::save(&path, &m).unwrap();
        assert_eq!(mesh::load(&path).unwrap().format, format);
    }
    let e = mesh::save(&dir.path().join("c.ply"), &m).unwrap_err();
    assert!(e.to_string().contains(".stl or .obj"), "{e}");
    let e = mesh::save(Path::new("/nonexistent-dir/x.obj"), &m).unwrap_err();
    assert!(e.to_string().contains("/nonexistent-dir/x.obj"), "{e}");
    // Only the finished file is there: no temporary files left behind.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    let e = mesh::load(&dir.path().join("missing.stl")).unwrap_err();
    assert!(e.to_string().contains("missing.stl"), "{e}");
}

#[test]
fn mutated_inputs_never_panic() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut obj = Vec::new();
    mesh::write_obj(&mut obj, &tetrahedron()).unwrap();
    let seeds: Vec<Vec<u8>> = vec![
        binary_stl(&tetrahedron(), b"solid x"),
        ASCII_STL.as_bytes().to_vec(),
        obj,
        three_mf(&[(
            "3D/3dmodel.model",
            &model_xml(TETRA_VERTICES, TETRA_TRIANGLES, ""),
        )]),
    ];
    for seed in &seeds {
        for _ in 0..400 {
            let mut bytes = seed.clone();
            match rng.random_range(0..3) {
                0 => {
                    let i = rng.random_range(0..bytes.len());
                    bytes[i] = rng.random();
                }
                1 => bytes.truncate(rng.random_range(0..bytes.len())),
                _ => {
                    let i = rng.random_range(0..bytes.len());
                    bytes.insert(i, rng.random());
                }
            }
            // Any outcome but a panic is fine; errors must name the source.
            if let Err(e) = read(&bytes) {
                assert!(e.to_string().contains("test-input"), "{e}");
            }
        }
    }
}

/// A 3MF whose build places several objects is a plate of several models: each object is
/// a run of the loaded mesh's faces, named as the file names it (or by its id), with the
/// runs moved past the faces cleaning dropped; an assembly (one build item of several
/// components) stays one model.
#[test]
fn three_mf_objects_of_a_build_are_kept_apart() {
    let degenerate = r#"<triangle v1="0" v2="0" v3="1"/>"#;
    let root = format!(
        r#"<?xml version="1.0"?>
<model unit="millimeter" xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02">
 <resources>
  <object id="1" name="Rook"><mesh><vertices>{TETRA_VERTICES}</vertices><triangles>{degenerate}{TETRA_TRIANGLES}</triangles></mesh></object>
  <object id="2"><mesh><vertices>{TETRA_VERTICES}</vertices><triangles>{TETRA_TRIANGLES}{degenerate}</triangles></mesh></object>
  <object id="3" name="  "><mesh><vertices>{TETRA_VERTICES}</vertices><triangles>{degenerate}</triangles></mesh></object>
 </resources>
 <build><item objectid="1"/><item objectid="3"/><item objectid="2" transform="2 0 0 0 2 0 0 0 2 10 0 0"/></build>
</model>"#
    );
    let loaded = read(&three_mf(&[("3D/3dmodel.model", &root)])).unwrap();
    assert_eq!(loaded.clean.dropped_degenerate_faces, 3);
    // The object of degenerate faces alone has none left: it is no part of the plate.
    let objects: Vec<(&str, std::ops::Range<usize>)> = loaded
        .objects
        .iter()
        .map(|o| (o.name.as_str(), o.faces.clone()))
        .collect();
    assert_eq!(objects, [("Rook", 0..4), ("object 2", 4..8)]);
    let second = loaded.mesh.sub(4..8);
    assert_eq!(second.faces, tetrahedron().faces);
    let doubled: Vec<[f64; 3]> = tetrahedron()
        .vertices
        .iter()
        .map(|v| [2.0 * v[0] + 10.0, 2.0 * v[1], 2.0 * v[2]])
        .collect();
    assert_eq!(second.vertices, doubled);
    assert_eq!(loaded.mesh.sub(0..4), tetrahedron());

    // One build item, however many components: one model.
    let one = read(&three_mf(&[(
        "3D/3dmodel.model",
        &model_xml(TETRA_VERTICES, TETRA_TRIANGLES, ""),
    )]))
    .unwrap();
    assert!(one.objects.is_empty());
}
