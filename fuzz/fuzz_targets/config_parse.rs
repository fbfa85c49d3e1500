//! Any text as the daemon's config file: an error naming where, or a config whose every
//! value is within its bounds; never a panic (a value that once panicked at reload is
//! exactly what this looks for).
#![no_main]

use crispen::daemon::config::Config;
use crispen::slice::HEIGHT_MM;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    match Config::parse(text, std::path::Path::new("/etc/crispen/crispen.toml")) {
        Ok(config) => {
            assert!(config.farm.max_heating >= 1);
            let host = &config.farm.host;
            assert!(!host.is_empty() && host.len() <= 64 && !host.starts_with(['.', '-']));
            if let Some(http) = &config.http {
                assert!(http.listen.port() == 0 || http.listen.port() >= 1024);
            }
            for folder in &config.folders {
                assert!(HEIGHT_MM.contains(&folder.height_mm));
                assert!(!folder.path.starts_with(&config.spool_dir));
            }
        }
        Err(e) => assert!(e.to_string().starts_with("/etc/crispen/crispen.toml")),
    }
});
