//! `crispen bed-check EMPTY.jpg FRAME.jpg [--region X,Y,W,H] [--json]`: the daemon's bed
//! check on two pictures, for an operator setting up a camera (which region, which light)
//! and for tests. Exit status 0 when the bed is clear, 1 when it is not, 2 on an error.

use anyhow::Context;
use crispen::bedcheck::{Reference, Region};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    /// The empty bed (the reference), a JPEG
    pub empty: PathBuf,
    /// The frame to check, a JPEG of the same camera and size
    pub frame: PathBuf,
    /// The bed's region in the pictures, pixels: left,top,width,height (default: all of it)
    #[arg(long, value_parser = Region::parse)]
    pub region: Option<Region>,
    /// The bed's width and depth in mm, for the patches' sizes (e.g. 223,223)
    #[arg(long, value_parser = bed_mm)]
    pub bed_mm: Option<[f64; 2]>,
    /// Write the frame with the region and the differing patches marked (a JPEG)
    #[arg(long)]
    pub marked: Option<PathBuf>,
    /// Print the answer as one JSON object
    #[arg(long)]
    pub json: bool,
}

fn bed_mm(text: &str) -> Result<[f64; 2], String> {
    let v: Vec<f64> = text
        .split([',', 'x'])
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{text:?}: {e}"))?;
    match v.as_slice() {
        &[w, d] if (1.0..=2000.0).contains(&w) && (1.0..=2000.0).contains(&d) => Ok([w, d]),
        _ => Err(format!(
            "{text:?}: give the bed as WIDTH,DEPTH in mm (each from 1 to 2000)"
        )),
    }
}

/// The largest picture read (a camera's frame is a few hundred kB).
const MAX_FILE_BYTES: u64 = 64 * 1024 * 1024;

fn read(path: &PathBuf) -> anyhow::Result<Vec<u8>> {
    use std::io::Read;
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_FILE_BYTES + 1).read_to_end(&mut bytes))
        .with_context(|| format!("cannot read {}", path.display()))?;
    anyhow::ensure!(
        bytes.len() as u64 <= MAX_FILE_BYTES,
        "{}: larger than {} MiB, not a camera's picture",
        path.display(),
        MAX_FILE_BYTES >> 20
    );
    Ok(bytes)
}

pub(crate) fn run(a: Args) -> anyhow::Result<ExitCode> {
    // 1 is "not clear": an error must not read as an answer.
    check(a).or_else(|e| {
        eprintln!("error: {}", super::error::describe(&e));
        Ok(ExitCode::from(2))
    })
}

fn check(a: Args) -> anyhow::Result<ExitCode> {
    let empty = read(&a.empty)?;
    let frame = read(&a.frame)?;
    let reference = Reference::prepare(&empty, a.region, a.bed_mm)
        .with_context(|| format!("{}", a.empty.display()))?;
    let verdict = reference
        .check(&frame)
        .with_context(|| format!("{}", a.frame.display()))?;
    if let Some(out) = &a.marked {
        let jpeg = crispen::bedcheck::marked_jpeg(&frame, &verdict)?;
        std::fs::write(out, jpeg).with_context(|| format!("cannot write {}", out.display()))?;
    }
    if a.json {
        println!("{}", serde_json::to_string(&verdict)?);
    } else {
        println!("{}", verdict.summary());
        for p in &verdict.patches {
            let size = p
                .size_mm
                .map(|[w, h]| format!(" ({w:.0} × {h:.0} mm)"))
                .unwrap_or_default();
            println!(
                "  patch at {},{} size {}x{} px{size}, {} px differ",
                p.x, p.y, p.w, p.h, p.area_px
            );
        }
        println!(
            "  region {}, camera shift {:.1},{:.1} px, light {:.2}× the reference's, threshold {:.1} levels",
            verdict.region, verdict.shift_px[0], verdict.shift_px[1], verdict.light, verdict.threshold
        );
    }
    Ok(if verdict.clear {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}
