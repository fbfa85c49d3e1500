//! The Spoolman client against the real server (`CRISPEN_SPOOLMAN_DIR`; each test starts
//! its own, and is `ignore`d with the reason where the variable was unset at build time):
//! spools read as the farm needs them, a spool outside the farm's bounds set aside alone
//! with why, filament used booked to the milligram, and Spoolman's errors and absence
//! named as they are.

use crate::common::spoolman::SpoolmanServer;
use crispen::outbound::HttpUrl;
use crispen::spoolman::{Spoolman, SpoolmanError, SpoolmanSpool};
use std::time::{Duration, Instant};

const TIMEOUT: Duration = Duration::from_secs(5);

fn client(url: &str) -> Spoolman {
    Spoolman::new(HttpUrl::parse(url).unwrap(), TIMEOUT)
}

fn block_on<F: std::future::Future>(future: F) -> F::Output {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(future)
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-6
}

/// Every spool is listed, archived ones flagged, each with its filament's material,
/// colour, brand and diameter, the weight left and the price per kg as created.
#[cfg_attr(
    not(crispen_spoolman),
    ignore = "CRISPEN_SPOOLMAN_DIR was unset at build time"
)]
#[test]
fn spools_are_listed_as_created() {
    let server = SpoolmanServer::start();
    let petg = server.create_spool("PETG", "000000", "Prusament", 1000.0, 100.0, 25.0, 1.75);
    let pla = server.create_spool("PLA", "FF8800", "Polymaker", 750.0, 0.0, 19.99, 2.85);
    // A second spool of the same brand, used up and archived.
    let old = server.create_spool("PLA", "FFFFFF", "Prusament", 1000.0, 1000.0, 30.0, 1.75);
    server.archive(old);
    let spoolman = client(&server.url);
    assert_eq!(spoolman.url(), server.url);

    let list = block_on(async {
        spoolman.health().await.unwrap();
        spoolman.spools().await.unwrap()
    });
    assert_eq!(list.set_aside, [], "{list:#?}");
    let spools = list.spools;
    let by_id = |id: u64| -> &SpoolmanSpool {
        spools
            .iter()
            .find(|s| s.id == id)
            .unwrap_or_else(|| panic!("no spool {id} in {spools:#?}"))
    };
    assert_eq!(spools.len(), 3, "{spools:#?}");

    let s = by_id(petg);
    assert_eq!(
        (
            s.material.as_deref(),
            s.colour_hex.as_deref(),
            s.brand.as_deref(),
            s.filament_name.as_deref()
        ),
        (
            Some("PETG"),
            Some("000000"),
            Some("Prusament"),
            Some("PETG 000000")
        ),
        "{s:#?}"
    );
    assert!(
        close(s.diameter_mm, 1.75) && close(s.density_g_cm3, 1.27),
        "{s:#?}"
    );
    assert_eq!(
        (s.initial_g, s.used_g, s.remaining_g),
        (Some(1000.0), 100.0, Some(900.0))
    );
    assert!(close(s.price_per_kg.unwrap(), 25.0), "{s:#?}");
    assert!(!s.archived);

    let s = by_id(pla);
    assert_eq!(
        (
            s.material.as_deref(),
            s.colour_hex.as_deref(),
            s.brand.as_deref()
        ),
        (Some("PLA"), Some("FF8800"), Some("Polymaker")),
        "{s:#?}"
    );
    assert!(close(s.diameter_mm, 2.85), "{s:#?}");
    assert_eq!(
        (s.initial_g, s.used_g, s.remaining_g),
        (Some(750.0), 0.0, Some(750.0))
    );
    assert!(close(s.price_per_kg.unwrap(), 19.99), "{s:#?}");

    let s = by_id(old);
    assert!(s.archived, "{s:#?}");
    assert_eq!(
        (s.brand.as_deref(), s.remaining_g),
        (Some("Prusament"), Some(0.0))
    );

    // One spool asked for alone reads the same as in the list.
    let one = block_on(spoolman.spool(pla)).unwrap();
    assert_eq!(&one, by_id(pla));
}

/// Spools Spoolman takes but the farm would not (outside the bounds of a spool of the
/// farm's own, made through Spoolman's own API) are each set aside with the field and
/// bound they break, and only they: the good ones around them are read as ever (they
/// were all taken as they were). A spool asked for alone is refused with the same reason.
/// Spoolman's API refuses a negative weight and a zero diameter itself, and shows a
/// spool used past its weight with 0 g left (taken: it is empty); such values from a
/// server are the list test's in `spoolman`, where one once failed the whole list.
#[cfg_attr(
    not(crispen_spoolman),
    ignore = "CRISPEN_SPOOLMAN_DIR was unset at build time"
)]
#[test]
fn spools_outside_the_farms_bounds_are_set_aside_alone() {
    use serde_json::json;
    let server = SpoolmanServer::start();
    let first = server.create_spool("PLA", "FFFFFF", "Acme", 1000.0, 0.0, 20.0, 1.75);
    // Used past its weight: Spoolman shows 0 g left, which a spool may have.
    let empty = server.create_spool("PLA", "FF0000", "Acme", 100.0, 150.0, 20.0, 1.75);
    let pla = |extra: serde_json::Value| {
        let mut filament =
            json!({"material": "PLA", "density": 1.24, "diameter": 1.75, "weight": 1000.0});
        for (k, v) in extra.as_object().unwrap() {
            filament[k] = v.clone();
        }
        filament
    };
    let bad: Vec<(u64, &str)> = vec![
        // Spoolman itself answers 500 for its whole list with 1e308 g (a length it cannot
        // write in JSON): 1e300 g is as much as it serves.
        (
            server.create_raw(pla(json!({})), json!({"initial_weight": 1e300})),
            "initial_weight: 0 to 100000 g, got 1e300",
        ),
        (
            server.create_raw(pla(json!({"diameter": 0.001})), json!({})),
            "diameter_mm: 1 to 3.5 mm, got 0.001",
        ),
        (
            server.create_raw(pla(json!({"density": 80.0})), json!({})),
            "density: 0.5 to 5 g/cm³, got 80",
        ),
        (
            server.create_raw(pla(json!({"material": "PLA\u{202e}GTEP"})), json!({})),
            "material: \"PLA\\u{202e}GTEP\" contains characters that reverse",
        ),
        (
            server.create_raw(pla(json!({"material": "P".repeat(50)})), json!({})),
            "material: 1 to 40 characters",
        ),
        (
            server.create_raw(pla(json!({"price": 1e9})), json!({})),
            "price_per_kg: 0 to 100000",
        ),
    ];
    let last = server.create_spool("PETG", "000000", "Acme", 500.0, 100.0, 30.0, 1.75);
    let spoolman = client(&server.url);
    let list = block_on(spoolman.spools()).unwrap();
    let taken: Vec<u64> = list.spools.iter().map(|s| s.id).collect();
    assert_eq!(taken, [first, empty, last], "{list:#?}");
    assert_eq!(list.spools[1].for_farm().unwrap().1, Some(0.0));
    assert_eq!(list.set_aside.len(), bad.len(), "{list:#?}");
    for (id, why) in &bad {
        let aside = list
            .set_aside
            .iter()
            .find(|a| a.spoolman == Some(*id))
            .unwrap_or_else(|| panic!("spool {id} is not set aside: {list:#?}"));
        assert!(
            aside.reason.starts_with(&format!("spool {id}: ")) && aside.reason.contains(why),
            "spool {id}: {} (expected {why})",
            aside.reason
        );
        // Alone, the same spool is refused with the same reason.
        let alone = block_on(spoolman.spool(*id)).unwrap_err();
        assert!(
            matches!(alone, SpoolmanError::BadAnswer { .. }) && alone.to_string().contains(why),
            "{alone}"
        );
    }
}

/// Filament used is taken off the spool exactly, by Spoolman as the client reads it.
#[cfg_attr(
    not(crispen_spoolman),
    ignore = "CRISPEN_SPOOLMAN_DIR was unset at build time"
)]
#[test]
fn use_weight_subtracts_exactly() {
    let server = SpoolmanServer::start();
    let id = server.create_spool("PETG", "1E90FF", "Prusament", 1000.0, 100.0, 25.0, 1.75);
    let spoolman = client(&server.url);
    let after = block_on(spoolman.use_weight(id, 12.345)).unwrap();
    assert_eq!(after.id, id);
    assert!(close(after.used_g, 100.0 + 12.345), "{after:#?}");
    assert!(
        close(after.remaining_g.unwrap(), 1000.0 - 100.0 - 12.345),
        "{after:#?}"
    );
    // Spoolman kept it: its own JSON and a fresh read agree with the answer.
    let json = server.spool_json(id);
    assert!(
        close(json["used_weight"].as_f64().unwrap(), 112.345),
        "{json}"
    );
    assert_eq!(block_on(spoolman.spool(id)).unwrap(), after);
    // A second print's filament adds to the first.
    let again = block_on(spoolman.use_weight(id, 0.655)).unwrap();
    assert!(close(again.remaining_g.unwrap(), 887.0), "{again:#?}");
}

/// A spool Spoolman does not have is its 404, with its own message.
#[cfg_attr(
    not(crispen_spoolman),
    ignore = "CRISPEN_SPOOLMAN_DIR was unset at build time"
)]
#[test]
fn an_unknown_spool_is_named_by_spoolman() {
    let server = SpoolmanServer::start();
    let spoolman = client(&server.url);
    for error in [
        block_on(spoolman.spool(99)).unwrap_err(),
        block_on(spoolman.use_weight(99, 1.0)).unwrap_err(),
    ] {
        let text = error.to_string();
        match &error {
            SpoolmanError::Status {
                status: 404,
                message: Some(m),
                ..
            } => assert_eq!(m, "No spool with ID 99 found.", "{text}"),
            other => panic!("not a 404 with a message: {other:?}"),
        }
        assert!(
            text.contains("404") && text.contains("No spool with ID 99 found."),
            "{text}"
        );
    }
}

/// Once the server is gone, a request fails at once, naming where it tried.
#[cfg_attr(
    not(crispen_spoolman),
    ignore = "CRISPEN_SPOOLMAN_DIR was unset at build time"
)]
#[test]
fn a_stopped_server_is_a_connect_error() {
    let server = SpoolmanServer::start();
    let url = server.url.clone();
    let spoolman = client(&url);
    block_on(spoolman.health()).unwrap();
    drop(server);
    let started = Instant::now();
    let error = block_on(spoolman.spools()).unwrap_err();
    assert!(started.elapsed() < TIMEOUT, "{:?}", started.elapsed());
    let host_port = url.strip_prefix("http://").unwrap();
    assert!(
        matches!(error, SpoolmanError::Connect { .. }) && error.to_string().contains(host_port),
        "{error}"
    );
}
