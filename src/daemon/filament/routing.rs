//! Which printer may take a job: what the job asks ([`Asks`]) against what a printer
//! offers ([`Offer`]), and, when no printer can take it, why ([`Waiting`]: data, put in
//! the operator's words only where it is shown, "waiting for PETG black on a 0.4 mm
//! nozzle: loaded are PLA white (um2-a), PLA black (um2-b)").
//!
//! Filament is measured as a length: the net millimetres a job's G-code pushes, from the
//! follower that books what a print took ([`crate::marlin::motion::extruded_mm`]). One
//! rule tells it to the operator, in a job's status and in every reason alike: grams at
//! the density of the material the job asks, where crispen knows that density (its
//! materials' table: PLA, PETG, ABS, TPU); metres of filament otherwise ([`Need`]).

use super::{Filament, Spool};
use serde::{Deserialize, Serialize};
use std::fmt;

/// What a job asks of its printer, from its folder and its sidecar, or for the material,
/// from its file. Empty asks nothing.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Asks {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<String>,
    /// The material is the one its pre-sliced file was sliced for (PrusaSlicer's
    /// `filament_type`, Cura's material), not the folder's or the sidecar's: a printer
    /// known to hold another material does not take it, one whose filament is not known
    /// does.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub material_of_file: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub colour: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nozzle_mm: Option<f64>,
    /// The printer must carry every one of these tags (its group).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tags: Vec<String>,
    /// Higher first; equal ones oldest first.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub priority: i32,
}

fn is_zero(p: &i32) -> bool {
    *p == 0
}

/// Priorities a folder or a sidecar may give.
pub const PRIORITY: std::ops::RangeInclusive<i32> = -100..=100;
/// Tags a job may ask for, or a printer carry.
pub const MAX_TAGS: usize = 16;

/// Checks a tag: a short word (letters, digits, `-`, `_`).
pub fn check_tag(tag: &str) -> Result<(), String> {
    if tag.is_empty()
        || tag.len() > 40
        || !tag
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    {
        return Err(format!("tag {tag:?}: 1 to 40 letters, digits, '-' or '_'"));
    }
    Ok(())
}

impl Asks {
    pub fn is_empty(&self) -> bool {
        *self == Asks::default()
    }

    /// These asks with the material a pre-sliced file was sliced for, `material`, where
    /// the folder and the sidecar name none; checked as any operator-given name is (a
    /// file's text is anyone's), the error saying why it cannot be.
    pub fn with_file_material(mut self, material: Option<&str>) -> Result<Asks, String> {
        let (None, Some(m)) = (&self.material, material) else {
            return Ok(self);
        };
        // Cut before the check, whose message quotes it: one too long to pass is refused
        // all the same, and quoted within bounds.
        let m: String = m.trim().chars().take(41).collect();
        check_asks(Some(&m), None, None, None, None)
            .map_err(|(_, e)| format!("the material the file was sliced for: {e}"))?;
        self.material = Some(m.to_ascii_uppercase());
        self.material_of_file = true;
        Ok(self)
    }
}

/// Filament one print of a job needs on one machine: the net length its G-code for that
/// machine pushes, and what that weighs at the density of the material the job asks,
/// where crispen knows it ([`super::grams_per_mm`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Need {
    pub mm: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub g: Option<f64>,
}

impl Need {
    /// `mm` of this machine's filament, for a job asking `material`.
    pub fn of(mm: f64, material: Option<&str>, filament_mm: f64) -> Need {
        Need {
            mm,
            g: material
                .and_then(|m| super::grams_per_mm(m, filament_mm))
                .map(|per_mm| mm * per_mm),
        }
    }

    /// `mm` of the same filament, told as this need is: in grams at the same density
    /// where it has a weight, else in metres.
    fn tell(&self, mm: f64) -> String {
        match self.g.filter(|_| self.mm > 0.0) {
            Some(g) => {
                let g = mm * g / self.mm;
                if g < 10.0 {
                    format!("{g:.1} g")
                } else {
                    format!("{g:.0} g")
                }
            }
            None if mm < 10_000.0 => format!("{:.2} m", mm / 1000.0),
            None => format!("{:.1} m", mm / 1000.0),
        }
    }
}

/// What one printer offers a job.
#[derive(Debug, Clone)]
pub struct Offer<'a> {
    pub printer: &'a str,
    /// Its machine's name (a job has G-code, and a need, per machine).
    pub machine: &'a str,
    /// The spool on it, when one is recorded.
    pub spool: Option<&'a Spool>,
    /// Its filament: the spool's, else its config's default; None: unknown (it takes a
    /// job that asks for no material or colour, or only for its file's material).
    pub filament: Option<&'a Filament>,
    /// Nothing is loaded (the operator unloaded it): it takes no job.
    pub unloaded: bool,
    pub nozzle_mm: f64,
    pub hardened: bool,
    /// The filament diameter its machine is fed.
    pub machine_filament_mm: f64,
    pub tags: &'a [String],
    /// Filament promised to the job printing on it, mm (none when idle).
    pub reserved_mm: f64,
}

/// What a printer holds, as the status shows it (owned: it is published).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Holding {
    /// Its filament (the spool's, or its config's default); None: unknown, or unloaded.
    pub filament: Option<Filament>,
    pub spool: Option<String>,
    #[serde(default)]
    pub unloaded: bool,
    pub remaining_g: Option<f64>,
    /// Grams promised to the print under way.
    #[serde(default)]
    pub reserved_g: f64,
    pub nozzle_mm: f64,
    #[serde(default)]
    pub hardened: bool,
    #[serde(default)]
    pub tags: Vec<String>,
}

impl Holding {
    pub fn of(offer: &Offer) -> Holding {
        Holding {
            filament: offer.filament.cloned(),
            spool: offer.spool.map(|s| s.id.clone()),
            unloaded: offer.unloaded,
            remaining_g: offer.spool.and_then(Spool::remaining_g),
            reserved_g: offer
                .spool
                .map_or(0.0, |s| s.filament.grams(offer.reserved_mm)),
            nozzle_mm: offer.nozzle_mm,
            hardened: offer.hardened,
            tags: offer.tags.to_vec(),
        }
    }
}

/// Why a printer cannot take a job.
#[derive(Debug, Clone, PartialEq)]
pub enum Refusal {
    Unloaded,
    Material,
    Colour,
    Nozzle,
    Group,
    /// Its filament's diameter is not its machine's (a 1.75 mm spool on a 2.85 mm printer).
    Diameter {
        spool_mm: f64,
        machine_mm: f64,
    },
    /// The material needs a hardened nozzle.
    Abrasive,
    /// The spool has less than the job needs: `left_mm` of its filament, less what the
    /// print under way on it will take.
    Spool {
        need: Need,
        left_mm: f64,
    },
    /// Its machine cannot print the job's file: why, as the job's preparation found
    /// (made for another machine, beyond its bed, refused by the G-code policy); None
    /// when no G-code was made for its machine at all.
    Machine {
        machine: String,
        reason: Option<String>,
    },
}

/// Materials that wear a brass nozzle out (carbon and glass fibre fills, glow-in-the-dark).
pub(crate) fn abrasive(material: &str) -> bool {
    let m = material.to_ascii_uppercase();
    m.contains("-CF") || m.contains("-GF") || m.ends_with("CF") || m.contains("GLOW")
}

/// Whether `offer` may take a job asking `asks` that needs `need` on the offer's machine
/// (None: not known), and if not, the first reason.
pub fn refusal(asks: &Asks, need: Option<Need>, offer: &Offer) -> Option<Refusal> {
    if offer.unloaded {
        return Some(Refusal::Unloaded);
    }
    if !asks.tags.iter().all(|t| offer.tags.contains(t)) {
        return Some(Refusal::Group);
    }
    if asks
        .nozzle_mm
        .is_some_and(|n| (n - offer.nozzle_mm).abs() > 1e-6)
    {
        return Some(Refusal::Nozzle);
    }
    let same = |a: &str, b: &str| a.trim().eq_ignore_ascii_case(b.trim());
    if let Some(m) = &asks.material {
        let holds = offer.filament.map(|f| same(&f.material, m));
        // An operator's ask wants a printer known to hold it; a file's own material only
        // keeps it from a printer known to hold another.
        let refused = match asks.material_of_file {
            false => holds != Some(true),
            true => holds == Some(false),
        };
        if refused {
            return Some(Refusal::Material);
        }
    }
    if let Some(c) = &asks.colour {
        let matches = offer.filament.is_some_and(|f| {
            same(&f.colour, c)
                || f.colour_hex
                    .as_deref()
                    .is_some_and(|h| same(h, c.trim_start_matches('#')))
        });
        if !matches {
            return Some(Refusal::Colour);
        }
    }
    if let Some(f) = offer.filament {
        if (f.diameter_mm - offer.machine_filament_mm).abs() > 0.2 {
            return Some(Refusal::Diameter {
                spool_mm: f.diameter_mm,
                machine_mm: offer.machine_filament_mm,
            });
        }
        if abrasive(&f.material) && !offer.hardened {
            return Some(Refusal::Abrasive);
        }
    }
    if let (Some(need), Some(spool)) = (need, offer.spool) {
        // Compared as lengths: the spool's grams at its own density and diameter.
        let left_mm = spool
            .remaining_g()
            .map_or(f64::INFINITY, |g| g / spool.filament.grams(1.0))
            - offer.reserved_mm;
        if need.mm > left_mm {
            return Some(Refusal::Spool {
                need,
                left_mm: left_mm.max(0.0),
            });
        }
    }
    None
}

/// Why no printer can take a ready job: what it asks, and each printer that serves it
/// with why it cannot. Data; its `Display` is the operator's words.
#[derive(Debug, Clone)]
pub struct Waiting<'a> {
    pub asks: &'a Asks,
    pub refused: Vec<(Offer<'a>, Refusal)>,
}

/// `a`, `a and b`, `a, b and c`.
fn listed(items: &[String]) -> String {
    match items {
        [] => String::new(),
        [one] => one.clone(),
        [rest @ .., last] => format!("{} and {last}", rest.join(", ")),
    }
}

impl Asks {
    /// The filament it asks, in words (`PETG black`, `black filament`), if any.
    fn filament_words(&self) -> Option<String> {
        let of_file = if self.material_of_file {
            " (the file's material)"
        } else {
            ""
        };
        match (&self.material, &self.colour) {
            (Some(m), Some(c)) => Some(format!("{m} {c}{of_file}")),
            (Some(m), None) => Some(format!("{m}{of_file}")),
            (None, Some(c)) => Some(format!("{c} filament")),
            (None, None) => None,
        }
    }

    /// ` on a 0.6 mm nozzle in group big`: what it asks of the printer beyond its
    /// filament, each part with its preposition.
    fn printer_words(&self) -> String {
        let mut words = String::new();
        if let Some(n) = self.nozzle_mm {
            words += &format!(" on a {n} mm nozzle");
        }
        match self.tags.as_slice() {
            [] => {}
            [one] => words += &format!(" in group {one}"),
            tags => words += &format!(" in groups {}", listed(tags)),
        }
        words
    }
}

impl fmt::Display for Waiting<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let asks = self.asks;
        if self.refused.is_empty() {
            return f.write_str("waiting for a printer: none serves its folder");
        }
        // A spool is checked last: a printer refused for its spool holds everything else
        // the job asks, and the job lacks only filament there.
        let short: Vec<(&Offer, &Need, f64)> = self
            .refused
            .iter()
            .filter_map(|(o, r)| match r {
                Refusal::Spool { need, left_mm } => Some((o, need, *left_mm)),
                _ => None,
            })
            .collect();
        let printer = asks.printer_words();
        let filament = asks.filament_words();
        let wanted = match (
            short.iter().max_by(|a, b| a.1.mm.total_cmp(&b.1.mm)),
            &filament,
        ) {
            (Some((_, need, _)), _) => format!(
                "{} of {}{printer}",
                need.tell(need.mm),
                filament.as_deref().unwrap_or("filament")
            ),
            (None, Some(fil)) => format!("{fil}{printer}"),
            // No filament asked: the nozzle is what it waits for ("a 0.8 mm nozzle in
            // group big"), else any printer of its groups.
            (None, None) => match printer.strip_prefix(" on ") {
                Some(nozzle) => nozzle.to_string(),
                None => format!("a printer{printer}"),
            },
        };
        let mut parts = Vec::new();
        if !short.is_empty() {
            let left: Vec<String> = short
                .iter()
                .map(|(o, need, left_mm)| format!("{} has {}", o.printer, need.tell(*left_mm)))
                .collect();
            parts.push(left.join(", "));
        }
        let loaded: Vec<String> = self
            .refused
            .iter()
            .filter(|(_, r)| !matches!(r, Refusal::Spool { .. } | Refusal::Machine { .. }))
            .map(|(o, r)| {
                let holds = match (o.unloaded, o.filament) {
                    (true, _) => "nothing".to_string(),
                    (false, Some(f)) => f.describe(),
                    (false, None) => "unknown filament".to_string(),
                };
                let detail = match r {
                    Refusal::Nozzle => format!(", {} mm nozzle", o.nozzle_mm),
                    Refusal::Group if o.tags.is_empty() => ", no group".into(),
                    Refusal::Group => format!(", group {}", o.tags.join("+")),
                    Refusal::Diameter {
                        spool_mm,
                        machine_mm,
                    } => format!(", a {spool_mm} mm spool on a {machine_mm} mm machine"),
                    Refusal::Abrasive => ", brass nozzle".into(),
                    _ => String::new(),
                };
                format!("{holds} ({}{detail})", o.printer)
            })
            .collect();
        match loaded.len() {
            0 => {}
            1 => parts.push(format!("loaded is {}", loaded[0])),
            _ => parts.push(format!("loaded are {}", loaded.join(", "))),
        }
        for (o, r) in &self.refused {
            if let Refusal::Machine { machine, reason } = r {
                parts.push(match reason {
                    Some(why) => format!("{} cannot print it ({why})", o.printer),
                    None => format!(
                        "{} cannot print it (no G-code was made for its machine, {machine})",
                        o.printer
                    ),
                });
            }
        }
        write!(f, "waiting for {wanted}: {}", parts.join("; "))
    }
}

/// Checks what a folder, a sidecar or a printer asks or holds; the error names its key.
pub(crate) fn check_asks(
    material: Option<&str>,
    colour: Option<&str>,
    nozzle_mm: Option<f64>,
    tags: Option<&[String]>,
    priority: Option<i32>,
) -> Result<(), (&'static str, String)> {
    for (key, text) in [("material", material), ("colour", colour)] {
        if let Some(t) = text {
            super::check_name(t, super::MAX_NAME_CHARS).map_err(|m| (key, m))?;
        }
    }
    if let Some(n) = nozzle_mm {
        if !(0.1..=2.0).contains(&n) {
            return Err(("nozzle_mm", format!("0.1 to 2 mm, got {n}")));
        }
    }
    if let Some(tags) = tags {
        if tags.len() > MAX_TAGS {
            return Err((
                "tags",
                format!("at most {} tags, got {}", MAX_TAGS, tags.len()),
            ));
        }
        for t in tags {
            check_tag(t).map_err(|m| ("tags", m))?;
        }
    }
    if let Some(p) = priority {
        let range = PRIORITY;
        if !range.contains(&p) {
            return Err((
                "priority",
                format!("{} to {}, got {p}", range.start(), range.end()),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::filament::{Inventory, Report, Use};

    fn filament(material: &str, colour: &str) -> Filament {
        Filament {
            material: material.into(),
            colour: colour.into(),
            colour_hex: None,
            brand: None,
            diameter_mm: 2.85,
            density_g_cm3: 1.24,
            price_per_kg: None,
        }
    }

    fn offer<'a>(printer: &'a str, f: Option<&'a Filament>) -> Offer<'a> {
        Offer {
            printer,
            machine: "ultimaker2",
            spool: None,
            filament: f,
            unloaded: false,
            nozzle_mm: 0.4,
            hardened: false,
            machine_filament_mm: 2.85,
            tags: &[],
            reserved_mm: 0.0,
        }
    }

    /// Why no printer of `offers` can take a job asking `asks` and needing `need` on
    /// each, in words; None when one can.
    fn words(asks: &Asks, need: Option<Need>, offers: &[Offer]) -> Option<String> {
        let refused = offers
            .iter()
            .map(|o| refusal(asks, need, o).map(|r| (o.clone(), r)))
            .collect::<Option<_>>()?;
        Some(Waiting { asks, refused }.to_string())
    }

    #[test]
    fn a_job_goes_only_where_its_asks_are_met() {
        let (pla_w, petg_b) = (filament("PLA", "white"), filament("PETG", "black"));
        let asks = Asks {
            material: Some("petg".into()),
            colour: Some("Black".into()),
            ..Asks::default()
        };
        assert_eq!(refusal(&asks, None, &offer("a", Some(&petg_b))), None);
        assert_eq!(
            refusal(&asks, None, &offer("a", Some(&pla_w))),
            Some(Refusal::Material)
        );
        assert_eq!(
            refusal(&asks, None, &offer("a", None)),
            Some(Refusal::Material),
            "an unknown filament is not PETG"
        );
        // Asking nothing: any printer that has filament of its machine's diameter.
        assert_eq!(refusal(&Asks::default(), None, &offer("a", None)), None);
        let mut thin = petg_b.clone();
        thin.diameter_mm = 1.75;
        assert!(matches!(
            refusal(&Asks::default(), None, &offer("a", Some(&thin))),
            Some(Refusal::Diameter { .. })
        ));
        let nozzle = Asks {
            nozzle_mm: Some(0.6),
            ..Asks::default()
        };
        assert_eq!(
            refusal(&nozzle, None, &offer("a", None)),
            Some(Refusal::Nozzle)
        );
        let tags = ["big".to_string()];
        let grouped = Asks {
            tags: tags.to_vec(),
            ..Asks::default()
        };
        let mut big = offer("a", None);
        assert_eq!(refusal(&grouped, None, &big), Some(Refusal::Group));
        big.tags = &tags;
        assert_eq!(refusal(&grouped, None, &big), None);
        let cf = filament("PLA-CF", "black");
        assert_eq!(
            refusal(&Asks::default(), None, &offer("a", Some(&cf))),
            Some(Refusal::Abrasive)
        );
    }

    /// A file's own material keeps it from a printer holding another, not from one
    /// whose filament nobody recorded; the folder's or sidecar's comes first, and a
    /// file's name is checked as an operator's is.
    #[test]
    fn a_files_material_refuses_only_a_printer_holding_another() {
        let (pla, tpu) = (filament("PLA", "white"), filament("TPU", "red"));
        let asks = Asks::default().with_file_material(Some(" pla ")).unwrap();
        assert_eq!(
            (asks.material.as_deref(), asks.material_of_file),
            (Some("PLA"), true)
        );
        assert_eq!(refusal(&asks, None, &offer("a", Some(&pla))), None);
        assert_eq!(refusal(&asks, None, &offer("a", None)), None);
        assert_eq!(
            refusal(&asks, None, &offer("a", Some(&tpu))),
            Some(Refusal::Material)
        );
        let mut unloaded = offer("a", None);
        unloaded.unloaded = true;
        assert_eq!(refusal(&asks, None, &unloaded), Some(Refusal::Unloaded));
        // The folder or the sidecar says otherwise: theirs, asked as an operator's.
        let sidecar = Asks {
            material: Some("TPU".into()),
            ..Asks::default()
        };
        let asks = sidecar.clone().with_file_material(Some("PLA")).unwrap();
        assert_eq!(asks, sidecar);
        assert_eq!(refusal(&asks, None, &offer("a", Some(&tpu))), None);
        assert_eq!(
            refusal(&asks, None, &offer("a", None)),
            Some(Refusal::Material)
        );
        // Nothing named: nothing asked.
        assert_eq!(
            Asks::default().with_file_material(None),
            Ok(Asks::default())
        );
        for bad in ["", "PLA\u{7}", &"P".repeat(10_000)] {
            let e = Asks::default().with_file_material(Some(bad)).unwrap_err();
            assert!(
                e.starts_with("the material the file was sliced for: "),
                "{e}"
            );
            assert!(e.len() < 200, "quoted within bounds: {e}");
        }
    }

    #[test]
    fn a_job_bigger_than_the_spool_waits() {
        let mut inv = Inventory::default();
        let id = inv.add_spool(filament("PLA", "white"), 50.0).unwrap();
        inv.record_use(
            &id,
            "j#0",
            Use {
                job: "j".into(),
                printer: "a".into(),
                grams: 20.0,
                mm: 0.0,
                at_s: 0.0,
                report: Report::Local,
            },
        );
        let spool = &inv.spools[&id];
        let mut o = offer("a", Some(&spool.filament));
        o.spool = Some(spool);
        // mm of this filament per gram.
        let per_g = 1.0 / spool.filament.grams(1.0);
        let pla = |g: f64| Need::of(g * per_g, Some("PLA"), 2.85);
        assert_eq!(refusal(&Asks::default(), Some(pla(30.0)), &o), None);
        assert!(matches!(
            refusal(&Asks::default(), Some(pla(30.5)), &o),
            Some(Refusal::Spool { need, left_mm }) if (need.g.unwrap() - 30.5).abs() < 1e-9 && (left_mm - 30.0 * per_g).abs() < 1e-9
        ));
        // What the printer's current job will take is not there for the next one.
        o.reserved_mm = 10.0 * per_g;
        assert!(refusal(&Asks::default(), Some(pla(25.0)), &o).is_some());
        let why = words(&Asks::default(), Some(pla(42.0)), &[o.clone()]).unwrap();
        assert_eq!(why, "waiting for 42 g of filament: a has 20 g");
        // A material whose density crispen does not know: the need and what is left in
        // metres, the one unit both are told in.
        let unknown = Need::of(42.0 * per_g, Some("PA-CF"), 2.85);
        assert_eq!(unknown.g, None);
        let why = words(&Asks::default(), Some(unknown), &[o]).unwrap();
        assert_eq!(why, "waiting for 5.31 m of filament: a has 2.53 m");
    }

    /// Grams are told at the density of the material asked: PETG's, not PLA's, for a
    /// PETG job, whatever the spool's own figure.
    #[test]
    fn the_need_is_weighed_at_the_asked_materials_density() {
        let petg = Need::of(1000.0, Some("petg"), 1.75);
        let pla = Need::of(1000.0, Some("PLA"), 1.75);
        let ratio = petg.g.unwrap() / pla.g.unwrap();
        assert!((ratio - 1.27 / 1.24).abs() < 1e-12, "{ratio}");
        // 1 m of 1.75 mm PLA is about 3 g.
        assert!((pla.g.unwrap() - 2.98).abs() < 0.01);
        assert_eq!(Need::of(1000.0, None, 1.75).g, None);
        assert_eq!(Need::of(0.0, Some("PLA"), 1.75).tell(0.0), "0.00 m");
        assert_eq!(petg.tell(1000.0), "3.1 g");
        assert_eq!(Need::of(12_345.0, None, 1.75).tell(12_345.0), "12.3 m");
    }

    #[test]
    fn the_reason_names_what_is_missing_and_what_is_loaded() {
        let (pla_w, pla_b) = (filament("PLA", "white"), filament("PLA", "black"));
        let asks = Asks {
            material: Some("PETG".into()),
            colour: Some("black".into()),
            nozzle_mm: Some(0.4),
            ..Asks::default()
        };
        let offers = [offer("um2-a", Some(&pla_w)), offer("um2-b", Some(&pla_b))];
        assert_eq!(
            words(&asks, None, &offers).unwrap(),
            "waiting for PETG black on a 0.4 mm nozzle: loaded are PLA white (um2-a), PLA black (um2-b)"
        );
        let petg = filament("PETG", "black");
        let offers = [offer("um2-a", Some(&pla_w)), offer("um2-c", Some(&petg))];
        assert_eq!(words(&asks, None, &offers), None);
        assert_eq!(
            words(&asks, None, &[]).unwrap(),
            "waiting for a printer: none serves its folder"
        );
    }

    /// A printer whose machine cannot print the file is named with why, beside those
    /// short of filament and those holding another; each detail in its place.
    #[test]
    fn every_printer_left_out_is_named_with_why() {
        let petg = filament("PETG", "black");
        let mut inv = Inventory::default();
        let id = inv.add_spool(petg.clone(), 5.0).unwrap();
        let mut short = offer("c", Some(&inv.spools[&id].filament));
        short.spool = Some(&inv.spools[&id]);
        let pla = filament("PLA", "white");
        let mut thin = filament("PETG", "black");
        thin.diameter_mm = 1.75;
        let cf = filament("PETG-CF", "black");
        let tags = ["small".to_string()];
        let mut grouped = offer("f", Some(&petg));
        grouped.tags = &tags;
        let asks = Asks {
            material: Some("PETG".into()),
            ..Asks::default()
        };
        // 42 g at PETG's density (crispen's table: 1.27 g/cm³).
        let per_g = 1.0 / crate::daemon::filament::grams_per_mm("PETG", 2.85).unwrap();
        let need = Need::of(42.0 * per_g, Some("PETG"), 2.85);
        let refused = vec![
            (short.clone(), refusal(&asks, Some(need), &short).unwrap()),
            (offer("a", Some(&pla)), Refusal::Material),
            (offer("b", Some(&thin)), refusal(&asks, None, &offer("b", Some(&thin))).unwrap()),
            (offer("d", Some(&cf)), Refusal::Abrasive),
            (grouped, Refusal::Group),
            (
                offer("m", None),
                Refusal::Machine {
                    machine: "ultimaker2".into(),
                    reason: Some("x.gcode is not for the ultimaker2: it was sliced for 1.75 mm filament, the ultimaker2 takes 2.85 mm".into()),
                },
            ),
            (
                offer("n", None),
                Refusal::Machine {
                    machine: "marlin-175".into(),
                    reason: None,
                },
            ),
        ];
        let why = Waiting {
            asks: &asks,
            refused,
        }
        .to_string();
        // The spool's 5 g at its own 1.24 g/cm³ are told at PETG's 1.27, as the need is:
        // one density in one sentence.
        assert_eq!(
            why,
            "waiting for 42 g of PETG: c has 5.1 g; \
             loaded are PLA white (a), PETG black (b, a 1.75 mm spool on a 2.85 mm machine), \
             PETG-CF black (d, brass nozzle), PETG black (f, group small); \
             m cannot print it (x.gcode is not for the ultimaker2: it was sliced for 1.75 mm filament, the ultimaker2 takes 2.85 mm); \
             n cannot print it (no G-code was made for its machine, marlin-175)"
        );
    }

    /// Every combination of what a job may ask (material, the operator's or the file's;
    /// colour; nozzle; none, one or two groups), worded plainly and as a spool's lack.
    #[test]
    fn every_combination_of_asks_is_worded() {
        let materials = [
            (None, false, ""),
            (Some("PETG"), false, "PETG"),
            (Some("PLA"), true, "PLA (the file's material)"),
        ];
        let mut seen = 0;
        for (material, of_file, m_words) in materials {
            for colour in [None, Some("black")] {
                for nozzle in [None, Some(0.6)] {
                    for tags in [&[][..], &["big"][..], &["big", "fast"][..]] {
                        let asks = Asks {
                            material: material.map(String::from),
                            material_of_file: of_file,
                            colour: colour.map(String::from),
                            nozzle_mm: nozzle,
                            tags: tags.iter().map(|t| t.to_string()).collect(),
                            priority: 0,
                        };
                        let filament = match (material, colour) {
                            (Some(_), Some(c)) if of_file => {
                                format!("PLA {c} (the file's material)")
                            }
                            (Some(m), Some(c)) => format!("{m} {c}"),
                            (Some(_), None) => m_words.to_string(),
                            (None, Some(c)) => format!("{c} filament"),
                            (None, None) => String::new(),
                        };
                        let mut printer = String::new();
                        if let Some(n) = nozzle {
                            printer += &format!(" on a {n} mm nozzle");
                        }
                        printer += match tags.len() {
                            0 => "",
                            1 => " in group big",
                            _ => " in groups big and fast",
                        };
                        let plain = match (filament.is_empty(), nozzle) {
                            (false, _) => format!("{filament}{printer}"),
                            (true, Some(_)) => printer[4..].to_string(),
                            (true, None) => format!("a printer{printer}"),
                        };
                        let lacking = format!(
                            "20 g of {}{printer}",
                            if filament.is_empty() {
                                "filament"
                            } else {
                                &filament
                            }
                        );
                        // Worded plainly: a printer that holds nothing.
                        let mut empty = offer("p", None);
                        empty.unloaded = true;
                        let why = words(&asks, None, &[empty]).unwrap();
                        assert_eq!(why, format!("waiting for {plain}: loaded is nothing (p)"));
                        // Short of filament: a printer that has everything else.
                        let f = filament_for(&asks);
                        let tags_owned: Vec<String> = asks.tags.clone();
                        let mut inv = Inventory::default();
                        let id = inv.add_spool(f, 5.0).unwrap();
                        let spool = &inv.spools[&id];
                        let mut full = offer("q", Some(&spool.filament));
                        full.spool = Some(spool);
                        full.nozzle_mm = nozzle.unwrap_or(0.4);
                        full.tags = &tags_owned;
                        let need = Need {
                            mm: 1000.0,
                            g: Some(20.0),
                        };
                        let why = words(&asks, Some(need), &[full]).unwrap();
                        assert!(
                            why.starts_with(&format!("waiting for {lacking}: q has ")),
                            "{why} for {asks:?}"
                        );
                        for w in [&plain, &lacking] {
                            assert!(!w.contains("  ") && !w.starts_with(' '), "{w}");
                        }
                        seen += 1;
                    }
                }
            }
        }
        assert_eq!(seen, 36);
        // A few in full, as an operator reads them.
        let asks = |m: Option<&str>, c: Option<&str>, n: Option<f64>, t: &[&str]| Asks {
            material: m.map(String::from),
            colour: c.map(String::from),
            nozzle_mm: n,
            tags: t.iter().map(|t| t.to_string()).collect(),
            ..Asks::default()
        };
        let mut empty = offer("p", None);
        empty.unloaded = true;
        for (a, expected) in [
            (asks(None, None, Some(0.8), &[]), "waiting for a 0.8 mm nozzle: loaded is nothing (p)"),
            (asks(None, None, None, &["big"]), "waiting for a printer in group big: loaded is nothing (p)"),
            (asks(None, Some("red"), None, &[]), "waiting for red filament: loaded is nothing (p)"),
            (
                asks(Some("PETG"), Some("black"), Some(0.6), &["a", "b", "c"]),
                "waiting for PETG black on a 0.6 mm nozzle in groups a, b and c: loaded is nothing (p)",
            ),
        ] {
            assert_eq!(words(&a, None, &[empty.clone()]).unwrap(), expected);
        }
    }

    /// A filament that has what `asks` asks (PETG when it asks none).
    fn filament_for(asks: &Asks) -> Filament {
        filament(
            asks.material.as_deref().unwrap_or("PETG"),
            asks.colour.as_deref().unwrap_or("white"),
        )
    }
}
