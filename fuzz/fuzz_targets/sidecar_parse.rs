//! Any bytes as a model's sidecar: an error naming the sidecar, or overrides within
//! their bounds; never a panic.
#![no_main]

use crispen::daemon::job::parse_sidecar;
use crispen::slice::HEIGHT_MM;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = std::path::Path::new("model.stl.toml");
    match parse_sidecar(data, path) {
        Ok(sidecar) => {
            if let Some(h) = sidecar.height_mm {
                assert!(HEIGHT_MM.contains(&h));
            }
            if let Some(n) = sidecar.copies {
                assert!((1..=100).contains(&n));
            }
            if let Some(printers) = &sidecar.printers {
                assert!((1..=100).contains(&printers.len()));
                assert!(sidecar.copies.is_none() && sidecar.printer.is_none());
                for (i, p) in printers.iter().enumerate() {
                    assert!(!printers[..i].contains(p), "{p} twice");
                }
            }
        }
        Err(e) => assert!(e.contains("model.stl.toml")),
    }
});
