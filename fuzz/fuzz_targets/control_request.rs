//! Any bytes as a control-socket request line: refused with a reason or understood, never
//! a panic; an understood request means the same after a round trip.
#![no_main]

use crispen::daemon::control::{parse_request, Request};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    match parse_request(data) {
        Ok(request) => {
            let text = serde_json::to_string(&request).unwrap();
            let again: Request = parse_request(text.as_bytes()).unwrap();
            assert_eq!(again, request);
        }
        Err(reason) => assert!(reason.starts_with("bad request: ")),
    }
});
