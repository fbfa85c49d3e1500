//! What the farm's printers hold, and what its jobs ask of them.
//!
//! - [`Inventory`]: the farm's spools (its own, or Spoolman's as last read), which printer
//!   holds which, and a ledger of what each print took from each spool. The job store's
//!   task owns it and keeps it with the jobs (both stores), so a shared farm agrees.
//! - [`Asks`]: a job's material, colour, nozzle, printer group and priority, resolved from
//!   its folder and sidecar once it is prepared.
//! - [`routing`]: whether a printer may take a job, and why no printer can; a job's
//!   filament [`Need`], told in grams of the material it asks or in metres.
//!
//! Nothing here does I/O: the store persists the inventory, `spoolman` talks to Spoolman,
//! and the printers' supervisors measure what a print pushed.

pub mod routing;

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

pub use routing::{Asks, Need};

/// A filament as the routing and the accounting see it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Filament {
    /// `PLA`, `PETG`, ... (compared without regard to case).
    pub material: String,
    /// A colour's name (`black`); compared without regard to case.
    pub colour: String,
    /// `RRGGBB`, when known (shown as the tile's swatch).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub colour_hex: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub brand: Option<String>,
    pub diameter_mm: f64,
    pub density_g_cm3: f64,
    /// What a kilogram cost (the farm's currency); None: unknown, no cost is counted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub price_per_kg: Option<f64>,
}

impl Filament {
    /// `PETG black`.
    pub fn describe(&self) -> String {
        format!("{} {}", self.material, self.colour)
    }

    /// Grams of `mm` of this filament.
    pub fn grams(&self, mm: f64) -> f64 {
        mm * weight_per_mm(self.diameter_mm, self.density_g_cm3)
    }
}

/// Grams per mm of filament `diameter_mm` thick at `density_g_cm3`.
fn weight_per_mm(diameter_mm: f64, density_g_cm3: f64) -> f64 {
    let r_cm = diameter_mm / 20.0;
    0.1 * std::f64::consts::PI * r_cm * r_cm * density_g_cm3
}

/// Grams per mm of `material` `diameter_mm` thick, at the density crispen knows for it
/// (its materials' table, [`crate::slice::MATERIALS`]); None for a material it does not
/// know, whose need is then told as a length (`Need`).
pub fn grams_per_mm(material: &str, diameter_mm: f64) -> Option<f64> {
    crate::slice::MATERIALS
        .iter()
        .find(|m| m.name.eq_ignore_ascii_case(material.trim()))
        .map(|m| weight_per_mm(diameter_mm, m.density_g_cm3))
}

/// One spool: its filament, what was on it when crispen last learnt it from its source
/// (the weight entered, or Spoolman's remaining weight as last read), and the ledger of
/// the prints that took from it since.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Spool {
    pub id: String,
    #[serde(flatten)]
    pub filament: Filament,
    /// Grams on the spool as last learnt; None: unknown (no spool check is made).
    pub base_g: Option<f64>,
    /// Spoolman's id of this spool, when it comes from Spoolman.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spoolman: Option<u64>,
    /// Each print's use, by its key (`<job>#<n>`): a use is recorded once, whatever
    /// retries and restarts bring it again.
    #[serde(default)]
    pub uses: BTreeMap<String, Use>,
    /// Used up or taken away (Spoolman archived it, or it left Spoolman): kept for its
    /// ledger, never loaded again.
    #[serde(default)]
    pub archived: bool,
}

/// What one print took from a spool.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Use {
    pub job: String,
    pub printer: String,
    pub grams: f64,
    pub mm: f64,
    pub at_s: f64,
    pub report: Report,
}

/// Where a use stands with the spool's source.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "state")]
pub enum Report {
    /// crispen's own spool: the use counts against `base_g`.
    Local,
    /// Not yet told to Spoolman.
    Pending,
    /// Sent to Spoolman, its answer not yet recorded (a restart or a lost answer): whether
    /// it counted is read from Spoolman's `used_weight` against what it was before.
    Sending { used_before_g: f64 },
    /// Spoolman counted it; `base_g` (its remaining weight) includes it.
    Sent,
}

impl Spool {
    /// Grams left: the base less the uses it does not include yet.
    pub fn remaining_g(&self) -> Option<f64> {
        let base = self.base_g?;
        let open: f64 = self
            .uses
            .values()
            .filter(|u| u.report != Report::Sent)
            .map(|u| u.grams)
            .sum();
        Some(base - open)
    }

    /// `PETG black (s3)`.
    pub fn describe_filament(&self) -> String {
        format!("{} ({})", self.filament.describe(), self.id)
    }

    /// `PETG black (s3, 412 g left)`.
    pub fn describe(&self) -> String {
        match self.remaining_g() {
            Some(g) => format!("{} ({}, {g:.0} g left)", self.filament.describe(), self.id),
            None => format!("{} ({})", self.filament.describe(), self.id),
        }
    }
}

/// What a printer holds, as recorded: a spool, or nothing (unloaded). A printer with no
/// record holds its config's default filament, if it names one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "holds")]
pub enum Loaded {
    Spool { spool: String },
    Nothing,
}

/// The farm's spools and which printer holds which.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Inventory {
    #[serde(default)]
    pub spools: BTreeMap<String, Spool>,
    #[serde(default)]
    pub loaded: BTreeMap<String, Loaded>,
    /// The next id of a spool of crispen's own (`s<N>`).
    #[serde(default)]
    pub next_id: u64,
    /// Spoolman's spools not taken at its last read (outside the bounds of a spool of the
    /// farm's own), each with why: shown with the spools, never loaded. One the farm knew
    /// before stays as it was last read.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub set_aside: Vec<SetAside>,
    /// Each printer's care: what it has done, the work done on it, whether it is held (see
    /// `crate::daemon::care`). Kept in this document so that a print is counted in the
    /// same write, under the same lock, as the spools' ledgers.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub care: BTreeMap<String, crate::daemon::care::PrinterCare>,
}

/// A spool of Spoolman's the farm did not take, and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SetAside {
    /// Spoolman's id; None for an item of its list that is not even a spool.
    pub spoolman: Option<u64>,
    /// What is wrong with it (its field, the bound, the value).
    pub reason: String,
}

impl SetAside {
    /// The farm's id of the spool (`sm<id>`), when it has one.
    pub fn id(&self) -> Option<String> {
        self.spoolman.map(|sm| format!("sm{sm}"))
    }
}

/// An inventory change refused, in words for the operator.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilamentError {
    #[error("no spool {0:?} (hint: `crispen spools` lists them)")]
    NoSuchSpool(String),
    #[error("spool {0} is archived (used up or removed); load another")]
    Archived(String),
    #[error("spool {spool} was set aside when Spoolman was last read: {reason} (hint: correct it in Spoolman; it is read again every poll_s)")]
    SetAside { spool: String, reason: String },
    #[error("spool {spool} is loaded on {printer}; unload it there first")]
    LoadedElsewhere { spool: String, printer: String },
    #[error("{0}")]
    Invalid(String),
    /// A change of a printer's care record (kept in the same document) was refused.
    #[error(transparent)]
    Care(#[from] crate::daemon::care::CareError),
}

/// Bounds on what an operator may enter for a spool.
pub const MAX_SPOOL_G: f64 = 100_000.0;
pub const MAX_PRICE_PER_KG: f64 = 100_000.0;
pub const DIAMETER_MM: std::ops::RangeInclusive<f64> = 1.0..=3.5;
pub const DENSITY_G_CM3: std::ops::RangeInclusive<f64> = 0.5..=5.0;
/// Most spools one farm keeps (its own and Spoolman's).
pub const MAX_SPOOLS: usize = 10_000;

/// Longest material or colour name, in characters.
pub const MAX_NAME_CHARS: usize = 40;
/// Longest brand name, in characters.
pub const MAX_BRAND_CHARS: usize = 80;

/// Checks a name given to a filament (its material, colour or brand: by the operator, a
/// folder, a sidecar, or Spoolman): none of its characters a control or bidi character
/// (the one check of [`crate::names`]; blanks around it included, which are not kept),
/// and 1 to `max` characters without them. What is wrong, quoting the name.
pub fn check_name(text: &str, max: usize) -> Result<(), String> {
    let quoted = crate::names::printable(text);
    if let Some(problem) = crate::names::problem(text) {
        return Err(format!("\"{quoted}\" {problem}"));
    }
    let text = text.trim();
    if text.is_empty() || text.chars().count() > max {
        return Err(format!("1 to {max} characters, got \"{quoted}\""));
    }
    Ok(())
}

/// Checks a filament's text and numbers, trimming its names: the one check of a spool,
/// whether the operator entered it or Spoolman sent it.
pub fn check_filament(mut f: Filament) -> Result<Filament, FilamentError> {
    let bad = |m: String| Err(FilamentError::Invalid(m));
    for (key, text) in [("material", &f.material), ("colour", &f.colour)] {
        if let Err(m) = check_name(text, MAX_NAME_CHARS) {
            return bad(format!("{key}: {m}"));
        }
    }
    // No brand is said by leaving it out.
    f.brand = f.brand.filter(|b| !b.trim().is_empty());
    if let Some(b) = &f.brand {
        if let Err(m) = check_name(b, MAX_BRAND_CHARS) {
            return bad(format!("brand: {m}"));
        }
    }
    f.material = f.material.trim().to_ascii_uppercase();
    f.colour = f.colour.trim().to_ascii_lowercase();
    f.brand = f.brand.map(|b| b.trim().to_string());
    if let Some(h) = &f.colour_hex {
        let h = h.trim_start_matches('#');
        if h.len() != 6 || !h.chars().all(|c| c.is_ascii_hexdigit()) {
            return bad(format!("colour_hex: six hex digits (RRGGBB), got {h:?}"));
        }
        f.colour_hex = Some(h.to_ascii_lowercase());
    }
    let number = crate::names::number;
    if !DIAMETER_MM.contains(&f.diameter_mm) {
        return bad(format!(
            "diameter_mm: {} to {} mm, got {}",
            DIAMETER_MM.start(),
            DIAMETER_MM.end(),
            number(f.diameter_mm)
        ));
    }
    if !DENSITY_G_CM3.contains(&f.density_g_cm3) {
        return bad(format!(
            "density: {} to {} g/cm³, got {}",
            DENSITY_G_CM3.start(),
            DENSITY_G_CM3.end(),
            number(f.density_g_cm3)
        ));
    }
    if let Some(p) = f.price_per_kg {
        if !(0.0..=MAX_PRICE_PER_KG).contains(&p) {
            return bad(format!(
                "price_per_kg: 0 to {MAX_PRICE_PER_KG}, got {}",
                number(p)
            ));
        }
    }
    Ok(f)
}

/// Grams on a spool (what is on it, used, or its filament's weight), within bounds; what
/// is wrong otherwise.
pub fn grams_in_bounds(g: f64) -> Result<f64, String> {
    if (0.0..=MAX_SPOOL_G).contains(&g) {
        Ok(g)
    } else {
        Err(format!(
            "0 to {MAX_SPOOL_G} g, got {}",
            crate::names::number(g)
        ))
    }
}

/// Checks the grams on a spool.
pub fn check_grams(g: f64) -> Result<f64, FilamentError> {
    grams_in_bounds(g).map_err(|e| FilamentError::Invalid(format!("grams: {e}")))
}

impl Inventory {
    /// A new spool of crispen's own; its id.
    pub fn add_spool(&mut self, filament: Filament, grams: f64) -> Result<String, FilamentError> {
        let filament = check_filament(filament)?;
        let grams = check_grams(grams)?;
        if self.spools.len() >= MAX_SPOOLS {
            return Err(FilamentError::Invalid(format!(
                "the farm keeps at most {MAX_SPOOLS} spools"
            )));
        }
        self.next_id += 1;
        let id = format!("s{}", self.next_id);
        self.spools.insert(
            id.clone(),
            Spool {
                id: id.clone(),
                filament,
                base_g: Some(grams),
                spoolman: None,
                uses: BTreeMap::new(),
                archived: false,
            },
        );
        Ok(id)
    }

    /// The printer holding `spool`, if any.
    pub fn holder(&self, spool: &str) -> Option<&str> {
        self.loaded.iter().find_map(|(p, l)| match l {
            Loaded::Spool { spool: s } if s == spool => Some(p.as_str()),
            _ => None,
        })
    }

    /// Puts `spool` on `printer` (in place of whatever it held).
    pub fn load(&mut self, printer: &str, spool: &str) -> Result<(), FilamentError> {
        // Set aside at Spoolman's last read, whether the farm knew it before or not.
        if let Some(aside) = self
            .set_aside
            .iter()
            .find(|a| a.id().as_deref() == Some(spool))
        {
            return Err(FilamentError::SetAside {
                spool: spool.to_string(),
                reason: aside.reason.clone(),
            });
        }
        let s = self
            .spools
            .get(spool)
            .ok_or_else(|| FilamentError::NoSuchSpool(spool.to_string()))?;
        if s.archived {
            return Err(FilamentError::Archived(spool.to_string()));
        }
        if let Some(other) = self.holder(spool).filter(|p| *p != printer) {
            return Err(FilamentError::LoadedElsewhere {
                spool: spool.to_string(),
                printer: other.to_string(),
            });
        }
        self.loaded.insert(
            printer.to_string(),
            Loaded::Spool {
                spool: spool.to_string(),
            },
        );
        Ok(())
    }

    pub fn unload(&mut self, printer: &str) {
        self.loaded.insert(printer.to_string(), Loaded::Nothing);
    }

    /// The spool `printer` holds, if a spool is recorded on it.
    pub fn spool_on(&self, printer: &str) -> Option<&Spool> {
        match self.loaded.get(printer)? {
            Loaded::Spool { spool } => self.spools.get(spool),
            Loaded::Nothing => None,
        }
    }

    /// Records a print's use of `spool` under `key`, once: a key already in the ledger is
    /// left as it is (the use came again, from a retried write or a restart). Says whether
    /// it was new.
    pub fn record_use(&mut self, spool: &str, key: &str, mut usage: Use) -> bool {
        let Some(s) = self.spools.get_mut(spool) else {
            return false;
        };
        if s.uses.contains_key(key) {
            return false;
        }
        usage.report = if s.spoolman.is_some() {
            Report::Pending
        } else {
            Report::Local
        };
        s.uses.insert(key.to_string(), usage);
        true
    }

    /// The uses Spoolman has not counted yet: (spool id, key, Spoolman's id, use).
    pub fn unreported(&self) -> Vec<(String, String, u64, Use)> {
        self.spools
            .values()
            .filter_map(|s| s.spoolman.map(|sm| (s, sm)))
            .flat_map(|(s, sm)| {
                s.uses
                    .iter()
                    .filter(|(_, u)| matches!(u.report, Report::Pending | Report::Sending { .. }))
                    .map(move |(k, u)| (s.id.clone(), k.clone(), sm, u.clone()))
            })
            .collect()
    }

    /// Sets a use's report state (a use no longer in the ledger is left alone).
    pub fn set_report(&mut self, spool: &str, key: &str, report: Report, base_g: Option<f64>) {
        if let Some(s) = self.spools.get_mut(spool) {
            if let Some(u) = s.uses.get_mut(key) {
                u.report = report;
                if let Some(b) = base_g {
                    s.base_g = Some(b);
                }
            }
        }
    }

    /// Takes in Spoolman's spools as just read: each becomes (or updates) spool
    /// `sm<id>`; one `set_aside` (outside the farm's bounds) is listed with why, and one
    /// crispen knew stays as last read; a Spoolman spool crispen knew that is gone is
    /// archived. Says whether anything changed.
    pub fn take_spoolman(
        &mut self,
        spools: Vec<(u64, Filament, Option<f64>, bool)>,
        set_aside: Vec<SetAside>,
    ) -> bool {
        let before = self.clone();
        let mut seen: std::collections::BTreeSet<String> =
            set_aside.iter().filter_map(SetAside::id).collect();
        self.set_aside = set_aside;
        for (sm, filament, remaining, archived) in spools {
            let id = format!("sm{sm}");
            seen.insert(id.clone());
            let entry = self.spools.entry(id.clone()).or_insert_with(|| Spool {
                id: id.clone(),
                filament: filament.clone(),
                base_g: remaining,
                spoolman: Some(sm),
                uses: BTreeMap::new(),
                archived,
            });
            entry.filament = filament;
            entry.archived = archived;
            // A use on its way to Spoolman may or may not be in the weight just read:
            // the base waits for its answer.
            if !entry
                .uses
                .values()
                .any(|u| matches!(u.report, Report::Sending { .. }))
            {
                entry.base_g = remaining;
            }
        }
        for s in self.spools.values_mut() {
            if s.spoolman.is_some() && !seen.contains(&s.id) {
                s.archived = true;
            }
        }
        *self != before
    }
}

/// The names the colours of Spoolman's filaments are matched by, with a typical shade.
const PALETTE: &[(&str, [u8; 3])] = &[
    ("black", [0, 0, 0]),
    ("white", [255, 255, 255]),
    ("grey", [128, 128, 128]),
    ("silver", [192, 192, 192]),
    ("red", [200, 30, 30]),
    ("orange", [255, 130, 0]),
    ("yellow", [250, 220, 0]),
    ("green", [30, 160, 60]),
    ("blue", [30, 80, 200]),
    ("purple", [120, 50, 160]),
    ("pink", [240, 120, 170]),
    ("brown", [120, 70, 30]),
];

/// A colour's name for a filament known by its name and hex colour: a colour word in its
/// name (`PETG Black`), else the nearest of a few named colours, else `unknown`.
pub fn colour_name(name: Option<&str>, hex: Option<&str>) -> String {
    if let Some(name) = name {
        for word in name.split(|c: char| !c.is_alphanumeric()) {
            let word = word.to_ascii_lowercase();
            let word = if word == "gray" { "grey".into() } else { word };
            if PALETTE.iter().any(|(n, _)| *n == word) {
                return word;
            }
        }
    }
    let rgb = hex.and_then(|h| {
        let h = h.trim_start_matches('#');
        let v = u32::from_str_radix(h.get(..6)?, 16).ok()?;
        Some([(v >> 16) as u8, (v >> 8) as u8, v as u8])
    });
    match rgb {
        Some(rgb) => PALETTE
            .iter()
            .min_by_key(|(_, p)| {
                (0..3)
                    .map(|i| (i32::from(p[i]) - i32::from(rgb[i])).pow(2))
                    .sum::<i32>()
            })
            .map(|(n, _)| n.to_string())
            .unwrap_or_default(),
        None => "unknown".into(),
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn petg_black() -> Filament {
        Filament {
            material: "PETG".into(),
            colour: "black".into(),
            colour_hex: None,
            brand: None,
            diameter_mm: 2.85,
            density_g_cm3: 1.27,
            price_per_kg: Some(25.0),
        }
    }

    fn a_use(grams: f64) -> Use {
        Use {
            job: "0001-a".into(),
            printer: "p".into(),
            grams,
            mm: 0.0,
            at_s: 0.0,
            report: Report::Local,
        }
    }

    #[test]
    fn a_use_counts_once_whatever_brings_it_again() {
        let mut inv = Inventory::default();
        let id = inv.add_spool(petg_black(), 750.0).unwrap();
        assert!(inv.record_use(&id, "0001-a#0", a_use(12.5)));
        assert!(!inv.record_use(&id, "0001-a#0", a_use(12.5)));
        assert!(inv.record_use(&id, "0001-a#1", a_use(2.5)));
        assert_eq!(inv.spools[&id].remaining_g(), Some(735.0));
    }

    #[test]
    fn a_spool_is_on_one_printer_at_a_time() {
        let mut inv = Inventory::default();
        let id = inv.add_spool(petg_black(), 750.0).unwrap();
        inv.load("a", &id).unwrap();
        assert_eq!(
            inv.load("b", &id),
            Err(FilamentError::LoadedElsewhere {
                spool: id.clone(),
                printer: "a".into()
            })
        );
        inv.unload("a");
        inv.load("b", &id).unwrap();
        assert_eq!(inv.spool_on("b").map(|s| s.id.as_str()), Some(id.as_str()));
        assert_eq!(inv.spool_on("a"), None);
        assert!(matches!(
            inv.load("a", "s99"),
            Err(FilamentError::NoSuchSpool(_))
        ));
    }

    #[test]
    fn spoolman_uses_count_until_spoolman_has_them() {
        let mut inv = Inventory::default();
        let f = petg_black();
        assert!(inv.take_spoolman(vec![(7, f.clone(), Some(900.0), false)], vec![]));
        assert!(!inv.take_spoolman(vec![(7, f.clone(), Some(900.0), false)], vec![]));
        assert!(inv.record_use("sm7", "j#0", a_use(10.0)));
        assert_eq!(inv.spools["sm7"].remaining_g(), Some(890.0));
        assert_eq!(inv.unreported().len(), 1);
        inv.set_report(
            "sm7",
            "j#0",
            Report::Sending {
                used_before_g: 100.0,
            },
            None,
        );
        // A read while the use is on its way does not move the base.
        inv.take_spoolman(vec![(7, f.clone(), Some(890.0), false)], vec![]);
        assert_eq!(inv.spools["sm7"].remaining_g(), Some(890.0));
        inv.set_report("sm7", "j#0", Report::Sent, Some(890.0));
        assert_eq!(inv.spools["sm7"].remaining_g(), Some(890.0));
        assert!(inv.unreported().is_empty());
        // Gone from Spoolman: archived, never loaded again.
        inv.take_spoolman(vec![], vec![]);
        assert!(matches!(
            inv.load("p", "sm7"),
            Err(FilamentError::Archived(_))
        ));
    }

    /// A spool of Spoolman's set aside at a read is listed with why and never loaded,
    /// known before or not; one known before stays as last read (not archived: it is
    /// still Spoolman's), and is taken again once it is corrected.
    #[test]
    fn a_spool_set_aside_is_kept_as_last_read_and_never_loaded() {
        let mut inv = Inventory::default();
        let f = petg_black();
        inv.take_spoolman(vec![(7, f.clone(), Some(900.0), false)], vec![]);
        let aside = |sm: u64| SetAside {
            spoolman: Some(sm),
            reason: format!("spool {sm}: density: 0.5 to 5 g/cm³, got 80"),
        };
        assert!(inv.take_spoolman(vec![], vec![aside(7), aside(8)]));
        assert_eq!(inv.set_aside, [aside(7), aside(8)]);
        let kept = &inv.spools["sm7"];
        assert!(!kept.archived && kept.remaining_g() == Some(900.0));
        for id in ["sm7", "sm8"] {
            let e = inv.load("p", id).unwrap_err();
            assert!(matches!(e, FilamentError::SetAside { .. }), "{e}");
            assert!(e.to_string().contains("got 80"), "{e}");
        }
        // Corrected in Spoolman: taken, loadable.
        assert!(inv.take_spoolman(vec![(7, f, Some(800.0), false)], vec![]));
        assert!(inv.set_aside.is_empty());
        inv.load("p", "sm7").unwrap();
        assert_eq!(inv.spool_on("p").unwrap().remaining_g(), Some(800.0));
        assert!(!inv.spools.contains_key("sm8"));
    }

    #[test]
    fn bad_spools_are_refused_with_the_key() {
        let mut f = petg_black();
        f.diameter_mm = f64::NAN;
        let e = check_filament(f).unwrap_err().to_string();
        assert!(e.contains("diameter_mm"), "{e}");
        let mut f = petg_black();
        f.colour = "\u{7}".into();
        assert!(check_filament(f)
            .unwrap_err()
            .to_string()
            .contains("colour"));
        assert!(check_grams(-1.0).is_err());
        assert!(check_grams(f64::INFINITY).is_err());
    }

    #[test]
    fn colours_are_named_from_the_name_or_the_shade() {
        assert_eq!(colour_name(Some("PETG Black"), Some("ffffff")), "black");
        assert_eq!(colour_name(Some("Galaxy"), Some("0a0a10")), "black");
        assert_eq!(colour_name(Some("Space Gray"), None), "grey");
        assert_eq!(colour_name(None, Some("#f8f8f0")), "white");
        assert_eq!(colour_name(None, None), "unknown");
        assert_eq!(colour_name(None, Some("zz")), "unknown");
    }

    #[test]
    fn grams_follow_diameter_and_density() {
        // 1 m of 1.75 mm PLA is about 3 g.
        let mut f = petg_black();
        f.diameter_mm = 1.75;
        f.density_g_cm3 = 1.24;
        assert!((f.grams(1000.0) - 2.98).abs() < 0.01);
    }
}
