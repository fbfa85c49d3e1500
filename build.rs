//! Build-time facts for the tests: whether the real printer firmware's folder is set
//! (`CRISPEN_FIRMWARE_DIR`) and whether the real Spoolman server's is
//! (`CRISPEN_SPOOLMAN_DIR`). Tests that need one are `ignore`d without it, so a clone
//! without them shows those tests as ignored, with the reason, rather than as passed.

fn main() {
    println!("cargo::rerun-if-changed=build.rs");
    for (variable, cfg) in [
        ("CRISPEN_FIRMWARE_DIR", "crispen_firmware"),
        ("CRISPEN_SPOOLMAN_DIR", "crispen_spoolman"),
    ] {
        println!("cargo::rustc-check-cfg=cfg({cfg})");
        println!("cargo::rerun-if-env-changed={variable}");
        if std::env::var_os(variable).is_some_and(|dir| !dir.is_empty()) {
            println!("cargo::rustc-cfg={cfg}");
        }
    }
}
