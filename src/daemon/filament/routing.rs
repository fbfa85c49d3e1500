//! Which printer may take a job: what the job asks ([`Asks`]) against what a printer
//! offers ([`Offer`]), and, when no printer can take it, the reason in the operator's
//! words ("waiting for PETG black on a 0.4 mm nozzle: loaded are PLA white (um2-a)").

use super::{Filament, Spool};
use serde::{Deserialize, Serialize};

/// What a job asks of its printer, from its folder and its sidecar. Empty asks nothing.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Asks {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<String>,
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

    /// `PETG black on a 0.6 mm nozzle, group big`: what it asks, in words (empty when it
    /// asks nothing).
    pub fn describe(&self) -> String {
        let mut parts = Vec::new();
        let filament = [self.material.as_deref(), self.colour.as_deref()]
            .into_iter()
            .flatten()
            .collect::<Vec<_>>()
            .join(" ");
        if !filament.is_empty() {
            parts.push(filament);
        }
        if let Some(n) = self.nozzle_mm {
            parts.push(format!("on a {n} mm nozzle"));
        }
        if !self.tags.is_empty() {
            parts.push(format!("group {}", self.tags.join("+")));
        }
        parts.join(" ")
    }
}

/// What one printer offers a job.
#[derive(Debug, Clone)]
pub struct Offer<'a> {
    pub printer: &'a str,
    /// The spool on it, when one is recorded.
    pub spool: Option<&'a Spool>,
    /// Its filament: the spool's, else its config's default; None: unknown (it takes a
    /// job that asks for no material or colour).
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
    /// The spool has less than the job needs.
    Spool {
        need_g: f64,
        left_g: f64,
    },
}

/// Materials that wear a brass nozzle out (carbon and glass fibre fills, glow-in-the-dark).
fn abrasive(material: &str) -> bool {
    let m = material.to_ascii_uppercase();
    m.contains("-CF") || m.contains("-GF") || m.ends_with("CF") || m.contains("GLOW")
}

/// Whether `offer` may take a job asking `asks` that needs `need_mm` of filament (None: not
/// known), and if not, the first reason.
pub fn refusal(asks: &Asks, need_mm: Option<f64>, offer: &Offer) -> Option<Refusal> {
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
        if !offer.filament.is_some_and(|f| same(&f.material, m)) {
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
    if let (Some(mm), Some(spool)) = (need_mm, offer.spool) {
        let need = spool.filament.grams(mm);
        let left =
            spool.remaining_g().unwrap_or(f64::INFINITY) - spool.filament.grams(offer.reserved_mm);
        if need > left {
            return Some(Refusal::Spool {
                need_g: need,
                left_g: left.max(0.0),
            });
        }
    }
    None
}

/// Why no printer in `offers` can take the job, in words; None when one can.
pub fn waiting_reason(asks: &Asks, need_mm: Option<f64>, offers: &[Offer]) -> Option<String> {
    let refusals: Vec<(&Offer, Refusal)> = offers
        .iter()
        .map(|o| refusal(asks, need_mm, o).map(|r| (o, r)))
        .collect::<Option<_>>()?;
    if refusals.is_empty() {
        return Some("waiting for a printer: none serves its folder".into());
    }
    let wanted = match asks.describe() {
        d if d.is_empty() => "a printer".to_string(),
        d => d,
    };
    // A spool is checked last: a printer refused for its spool holds everything else the
    // job asks. Then the job lacks only filament: it says how much, and what is left where.
    let short: Vec<(&str, f64, f64)> = refusals
        .iter()
        .filter_map(|(o, r)| match r {
            Refusal::Spool { need_g, left_g } => Some((o.printer, *need_g, *left_g)),
            _ => None,
        })
        .collect();
    if !short.is_empty() {
        let need_g = short.iter().map(|s| s.1).fold(0.0, f64::max);
        let left: Vec<String> = short
            .iter()
            .map(|(p, _, left_g)| format!("{p} has {left_g:.0} g"))
            .collect();
        return Some(format!(
            "waiting for a spool with {need_g:.0} g for {wanted}: {}",
            left.join(", ")
        ));
    }
    let loaded: Vec<String> = refusals
        .iter()
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
                Refusal::Spool { left_g, .. } => format!(", {left_g:.0} g left"),
                _ => String::new(),
            };
            format!("{holds} ({}{detail})", o.printer)
        })
        .collect();
    Some(format!(
        "waiting for {wanted}: loaded are {}",
        loaded.join(", ")
    ))
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
        assert_eq!(refusal(&Asks::default(), Some(30.0 * per_g), &o), None);
        assert!(matches!(
            refusal(&Asks::default(), Some(30.5 * per_g), &o),
            Some(Refusal::Spool { need_g, left_g }) if (need_g - 30.5).abs() < 1e-9 && (left_g - 30.0).abs() < 1e-9
        ));
        // What the printer's current job will take is not there for the next one.
        o.reserved_mm = 10.0 * per_g;
        assert!(refusal(&Asks::default(), Some(25.0 * per_g), &o).is_some());
        let why = waiting_reason(&Asks::default(), Some(42.0 * per_g), &[o]).unwrap();
        assert_eq!(
            why,
            "waiting for a spool with 42 g for a printer: a has 20 g"
        );
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
            waiting_reason(&asks, None, &offers).unwrap(),
            "waiting for PETG black on a 0.4 mm nozzle: loaded are PLA white (um2-a), PLA black (um2-b)"
        );
        let petg = filament("PETG", "black");
        let offers = [offer("um2-a", Some(&pla_w)), offer("um2-c", Some(&petg))];
        assert_eq!(waiting_reason(&asks, None, &offers), None);
        assert_eq!(
            waiting_reason(&asks, None, &[]).unwrap(),
            "waiting for a printer: none serves its folder"
        );
    }
}
