//! Build-time facts for the tests: whether the real printer firmware's folder is set
//! (`CRISPEN_FIRMWARE_DIR`). Tests that need it are `ignore`d without it, so a clone
//! without the firmware shows them as ignored, with the reason, rather than as passed.

fn main() {
    println!("cargo::rustc-check-cfg=cfg(crispen_firmware)");
    println!("cargo::rerun-if-env-changed=CRISPEN_FIRMWARE_DIR");
    println!("cargo::rerun-if-changed=build.rs");
    if std::env::var_os("CRISPEN_FIRMWARE_DIR").is_some_and(|dir| !dir.is_empty()) {
        println!("cargo::rustc-cfg=crispen_firmware");
    }
}
