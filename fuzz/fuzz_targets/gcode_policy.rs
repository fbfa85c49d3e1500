//! Any bytes as G-code judged by the G-code policy (every file crispen prepares), for a
//! built-in machine that allows `M500`: a verdict within its bounds, never a panic, a hang
//! or runaway memory; every refusal names a line of the input.
#![no_main]

use crispen::machine::Machine;
use crispen::slice::policy::{check, MAX_LISTED};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let machine = Machine {
        allow: vec!["M500".into()],
        ..Machine::builtin("ultimaker2").expect("built in")
    };
    let v = check(data, &machine).expect("reading bytes cannot fail");
    let lines = data.split(|&b| b == b'\n').count();
    assert!(v.lines <= lines);
    assert!(v.refusals.len() <= MAX_LISTED && v.refusals.len() <= v.refusals_total);
    assert!(v.pauses.len() <= MAX_LISTED && v.pauses.len() <= v.pauses_total);
    assert_eq!(v.passed(), v.refusals_total == 0);
    for r in &v.refusals {
        assert!(r.line >= 1 && r.line <= v.lines, "{r}");
    }
    let _ = v.summary();
});
