//! `crispen load`, `crispen unload` and `crispen spools`: what each printer holds, through
//! the daemon's control socket (the same API the dashboard uses).

use super::control::ask;
use crispen::percent::percent_encode;
use hyper::Method;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, clap::Args)]
pub(crate) struct LoadArgs {
    /// Printer name, as in the config's [[printer]] name
    pub printer: String,
    /// A spool the farm knows (`crispen spools`): `s3`, or `sm12` for Spoolman's spool 12
    #[arg(long, conflicts_with_all = ["material", "colour", "grams"])]
    pub spool: Option<String>,
    /// A new spool's material (PLA, PETG, ABS, TPU, or your own name)
    #[arg(long, requires_all = ["colour", "grams"])]
    pub material: Option<String>,
    /// A new spool's colour, by name (black, white, ...)
    #[arg(long)]
    pub colour: Option<String>,
    /// Grams of filament on the new spool (without the spool itself)
    #[arg(long)]
    pub grams: Option<f64>,
    /// What a kilogram cost (for the history's cost)
    #[arg(long)]
    pub price_per_kg: Option<f64>,
    #[arg(long)]
    pub brand: Option<String>,
    /// RRGGBB, for the dashboard's swatch
    #[arg(long)]
    pub colour_hex: Option<String>,
    /// Filament diameter, mm (default: the printer's machine's)
    #[arg(long)]
    pub diameter_mm: Option<f64>,
    /// Density, g/cm³ (default: the material's)
    #[arg(long)]
    pub density: Option<f64>,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub(crate) struct SpoolsArgs {
    /// Archived (used up, or removed from Spoolman) spools too
    #[arg(long)]
    pub archived: bool,
    /// Print the daemon's JSON instead of the table
    #[arg(long)]
    pub json: bool,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

pub(crate) fn load(a: LoadArgs) -> anyhow::Result<ExitCode> {
    let mut query = Vec::new();
    let mut put = |key: &str, value: Option<String>| {
        if let Some(v) = value {
            query.push(format!("{key}={}", percent_encode(&v)));
        }
    };
    put("spool", a.spool);
    put("material", a.material);
    put("colour", a.colour);
    put("grams", a.grams.map(|g| g.to_string()));
    put("price_per_kg", a.price_per_kg.map(|p| p.to_string()));
    put("brand", a.brand);
    put("colour_hex", a.colour_hex);
    put("diameter_mm", a.diameter_mm.map(|d| d.to_string()));
    put("density_g_cm3", a.density.map(|d| d.to_string()));
    if query.is_empty() {
        anyhow::bail!(
            "say what to load: --spool ID, or a new spool's --material, --colour and --grams"
        );
    }
    let path = format!(
        "/api/v1/printers/{}/load?{}",
        percent_encode(&a.printer),
        query.join("&")
    );
    let answer = ask(&a.config, Method::POST, &path)?;
    println!("{}", answer["message"].as_str().unwrap_or_default());
    Ok(ExitCode::SUCCESS)
}

pub(crate) fn unload(a: super::control::PrinterArgs) -> anyhow::Result<ExitCode> {
    let path = format!("/api/v1/printers/{}/unload", percent_encode(&a.printer));
    let answer = ask(&a.config, Method::POST, &path)?;
    println!("{}", answer["message"].as_str().unwrap_or_default());
    Ok(ExitCode::SUCCESS)
}

pub(crate) fn spools(a: SpoolsArgs) -> anyhow::Result<ExitCode> {
    let path = format!("/api/v1/spools?archived={}", a.archived);
    let answer = ask(&a.config, Method::GET, &path)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&answer)?);
        return Ok(ExitCode::SUCCESS);
    }
    let spools = answer["spools"].as_array().cloned().unwrap_or_default();
    let set_aside = answer["set_aside"].as_array().cloned().unwrap_or_default();
    print_spools(&answer, &spools);
    if !set_aside.is_empty() {
        println!("\nset aside (not taken from Spoolman; correct them there):");
        for a in set_aside {
            println!(
                "{:<8} {}",
                crispen::names::printable(a["id"].as_str().unwrap_or("-")),
                crispen::names::escaped(a["reason"].as_str().unwrap_or(""))
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The table of spools (or a line saying there are none).
fn print_spools(answer: &serde_json::Value, spools: &[serde_json::Value]) {
    if spools.is_empty() {
        println!(
            "no spools ({}); load one with `crispen load PRINTER --material PLA --colour white --grams 750`",
            answer["source"].as_str().unwrap_or("crispen")
        );
        return;
    }
    println!(
        "{:<8} {:<8} {:<10} {:>10} {:>8} {:<12} BRAND",
        "SPOOL", "MATERIAL", "COLOUR", "LEFT", "PRICE/KG", "ON"
    );
    for s in spools {
        // Names as the farm shows them everywhere: a control or bidi character stored
        // before names were checked is escaped, never printed raw.
        let text = |k: &str| crispen::names::printable(s[k].as_str().unwrap_or("-"));
        let left = s["remaining_g"]
            .as_f64()
            .map_or("unknown".into(), |g| format!("{g:.1} g"));
        let price = s["price_per_kg"]
            .as_f64()
            .map_or("-".into(), |p| format!("{p:.2}"));
        let mut on = text("loaded_on");
        if s["archived"] == true {
            on = "archived".into();
        }
        println!(
            "{:<8} {:<8} {:<10} {:>10} {:>8} {:<12} {}",
            text("id"),
            text("material"),
            text("colour"),
            left,
            price,
            on,
            text("brand")
        );
    }
}
