//! The bed pictures of `tests/data/bed` (made by `scripts/make-bed-pictures`, described
//! in its `pictures.json`) and the bed check's answers on them: what the tests pin and
//! the `bedcheck` bench prints.

use crispen::bedcheck::{Reference, Region, Verdict};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::PathBuf;

pub fn dir() -> PathBuf {
    super::data_dir().join("bed")
}

/// `pictures.json`.
pub fn manifest() -> Value {
    serde_json::from_slice(&std::fs::read(dir().join("pictures.json")).unwrap()).unwrap()
}

pub fn read(file: &str) -> Vec<u8> {
    std::fs::read(dir().join(file)).unwrap_or_else(|e| panic!("{file}: {e}"))
}

fn region(v: &Value) -> Region {
    let n = |i: usize| v[i].as_u64().unwrap() as u32;
    Region {
        x: n(0),
        y: n(1),
        w: n(2),
        h: n(3),
    }
}

/// One picture of the set and the check's answer.
pub struct Case {
    pub file: String,
    /// What it shows: `empty`, `part`, `purge line`, `blob`, `spaghetti`.
    pub what: String,
    pub size_mm: Option<f64>,
    pub colour: Option<String>,
    pub light: String,
    /// Whether the bed is clear in it.
    pub clear: bool,
    pub verdict: Verdict,
}

/// Every picture of the set checked against its bed's reference.
pub fn check_all() -> Vec<Case> {
    let m = manifest();
    let region = region(&m["region"]);
    let bed_mm = [
        m["bed_mm"][0].as_f64().unwrap(),
        m["bed_mm"][1].as_f64().unwrap(),
    ];
    let mut references: BTreeMap<String, Reference> = BTreeMap::new();
    m["pictures"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let file = p["file"].as_str().unwrap().to_string();
            let reference_file = p["reference"].as_str().unwrap().to_string();
            let reference = references.entry(reference_file.clone()).or_insert_with(|| {
                Reference::prepare(&read(&reference_file), Some(region), Some(bed_mm)).unwrap()
            });
            let verdict = reference
                .check(&read(&file))
                .unwrap_or_else(|e| panic!("{file}: {e}"));
            Case {
                what: p["what"].as_str().unwrap().to_string(),
                size_mm: p["size_mm"].as_f64(),
                colour: p["colour"].as_str().map(str::to_string),
                light: p["light"].as_str().unwrap().to_string(),
                clear: p["clear"].as_bool().unwrap(),
                verdict,
                file,
            }
        })
        .collect()
}

/// The 1280 × 720 pair: the reference prepared, and the frame's bytes.
pub fn hd_pair() -> (Reference, Vec<u8>) {
    let m = manifest();
    let hd = &m["hd"];
    let reference = Reference::prepare(
        &read(hd["reference"].as_str().unwrap()),
        Some(region(&hd["region"])),
        Some([223.0, 223.0]),
    )
    .unwrap();
    (reference, read(hd["frame"].as_str().unwrap()))
}

/// The false "clear" and false "not clear" rates of `cases`, %: (false clear, of the
/// pictures with something on the bed; false not clear, of the empty ones).
pub fn rates(cases: &[Case]) -> (f64, f64) {
    let rate = |clear: bool| {
        let of: Vec<&Case> = cases.iter().filter(|c| c.clear == clear).collect();
        let wrong = of.iter().filter(|c| c.verdict.clear != clear).count();
        100.0 * wrong as f64 / of.len().max(1) as f64
    };
    (rate(false), rate(true))
}
