//! Any bytes as a mesh file (STL, OBJ, 3MF are sniffed from the content): an error or a
//! mesh, never a panic, and never more than the limits allow. Small limits keep each run
//! fast, so the fuzzer explores structure rather than size.
#![no_main]

use crispen::mesh::{self, Limits};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let limits = Limits {
        max_vertices: 20_000,
        max_faces: 40_000,
        max_bytes: 1 << 20,
        max_xml_bytes: 4 << 20,
        max_instances: 10_000,
    };
    if let Ok(loaded) = mesh::read_with_limits(std::io::Cursor::new(data), "fuzz", &limits) {
        assert!(loaded.mesh.vertices.len() <= limits.max_vertices);
        assert!(loaded.mesh.faces.len() <= limits.max_faces);
        let n = loaded.mesh.vertices.len();
        assert!(loaded
            .mesh
            .faces
            .iter()
            .flatten()
            .all(|&i| (i as usize) < n));
    }
});
