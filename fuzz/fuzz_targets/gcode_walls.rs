//! Any bytes as two G-code files (split at the first NUL, else in the middle) whose outer
//! walls are compared (`crispen slice --compare`, every enhanced job): figures within their
//! bounds, never a panic, a hang or runaway memory.
#![no_main]

use crispen::slice::walls::{compare, outer_walls, MAX_DISTANCE_MM};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let split = data
        .iter()
        .position(|&b| b == 0)
        .unwrap_or(data.len() / 2);
    let (plain, enhanced) = data.split_at(split);
    let (Ok(plain), Ok(enhanced)) = (outer_walls(plain), outer_walls(enhanced)) else {
        return;
    };
    let c = compare(&plain, &enhanced, 0.4);
    assert!(c.mean_mm.is_finite() && c.mean_mm >= 0.0 && c.mean_mm <= MAX_DISTANCE_MM);
    assert!(c.max_mm <= MAX_DISTANCE_MM && c.p95_mm <= c.max_mm);
    for share in [c.share_over_0_05_mm, c.share_over_0_1_mm, c.share_over_0_2_mm] {
        assert!((0.0..=1.0).contains(&share));
    }
});
