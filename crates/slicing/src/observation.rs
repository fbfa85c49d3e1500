//! What an observation is, as data: how the prints are looked at, how alike each looked
//! to the reference, and what was chosen. Kept apart from the observer that draws the
//! prints from their G-code and from the preparation step that slices them, so that a
//! slice report and the farm's settings can hold it without depending on either.

use serde::{Deserialize, Serialize};
use std::time::Duration;

/// How the prints are looked at.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Conditions {
    /// From the eye to the print, mm.
    pub distance_mm: f64,
    /// The resolution every print is drawn at, at least, pixels per degree: twice the
    /// highest frequency a person resolves (60 cycles per degree, where Barten's
    /// sensitivity at office luminance falls below 1).
    pub pixels_per_degree: f64,
    /// How far above the print's horizon the eye is, degrees.
    pub elevation_deg: f64,
    /// How many views, evenly around the print (the first from 45° to the front's left).
    pub views: usize,
}

impl Default for Conditions {
    /// A print on a table, looked at from 40 cm and from 30° above, walked around in four
    /// views.
    fn default() -> Self {
        Conditions {
            distance_mm: 400.0,
            pixels_per_degree: 120.0,
            elevation_deg: 30.0,
            views: 4,
        }
    }
}

/// The bounds of [`Conditions`].
pub const DISTANCE_MM: std::ops::RangeInclusive<f64> = 100.0..=5000.0;
pub const PIXELS_PER_DEGREE: std::ops::RangeInclusive<f64> = 30.0..=240.0;
pub const ELEVATION_DEG: std::ops::RangeInclusive<f64> = 0.0..=80.0;
pub const VIEWS: std::ops::RangeInclusive<usize> = 1..=8;

/// How alike a print looks to the reference.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Resemblance {
    /// 1 / (1 + the difference): 1 when nothing visible differs, higher is more alike.
    pub resemblance: f64,
    /// The visible difference, pooled over the bands, the places and the views, in
    /// multiples of the threshold (1: a difference a person sees half the time).
    pub difference_jnd: f64,
    /// The part of it where the reference shows more (features lost) and where the print
    /// shows more (features added: an over-enhanced surface, coarser layer lines).
    pub lost_jnd: f64,
    pub added_jnd: f64,
    /// Per band, finest first.
    pub bands: Vec<BandDifference>,
    /// Per view, the difference seen from it.
    pub views_jnd: Vec<f64>,
}

/// One octave band of the object: its frequency on the reference's retina and on this
/// print's (None where this print's picture has no such band: finer than it can show),
/// and what is lost and added in it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BandDifference {
    pub reference_cpd: f64,
    pub cpd: Option<f64>,
    pub lost_jnd: f64,
    pub added_jnd: f64,
}

/// How a candidate is made.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CandidateMode {
    /// The model unmodified.
    Plain,
    /// The paper's method at its λ2.
    Paper,
    /// The print-aware mode, its target from the strength (the height table's when none).
    PrintAware,
}

/// The observer's settings in a farm (`[enhancement]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObserveSettings {
    /// The size the small print should look like, mm (`reference_height_mm`): where the
    /// paper's table prints unmodified.
    pub reference_height_mm: f64,
    /// How long the observer may take (`observe_timeout_s`), within half the job's
    /// preparation time, so that the chosen print can still be made.
    pub timeout: Duration,
}

impl Default for ObserveSettings {
    fn default() -> Self {
        ObserveSettings {
            reference_height_mm: crispen_geometry::enhance::StrengthTable::default()
                .unmodified_from_mm,
            timeout: Duration::from_secs(DEFAULT_OBSERVE_TIMEOUT_S),
        }
    }
}

/// The default time bound of an observation, seconds: Spot at 50 mm takes about a
/// minute on two cores (see `benches/observe.rs`).
pub const DEFAULT_OBSERVE_TIMEOUT_S: u64 = 600;

/// What the observer found, and what it chose.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Observation {
    pub height_mm: f64,
    pub reference_height_mm: f64,
    /// The machine the prints were sliced for.
    pub machine: String,
    pub conditions: Conditions,
    pub candidates: Vec<Looked>,
    /// The candidate chosen (an index into `candidates`), when the observer chose.
    pub chosen: Option<usize>,
    pub choice: Choice,
    /// Why nothing was observed, when `choice` is `failed`: the error.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub failure: Option<String>,
    pub seconds: f64,
}

/// One candidate as the observer saw it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Looked {
    pub mode: CandidateMode,
    /// The λ2 it was made with (0: the plain print; print-aware: the one its search chose).
    pub strength: f64,
    /// How alike it looks to the reference (its `resemblance`, higher is more alike), when
    /// it was made and looked at.
    #[serde(flatten)]
    pub seen: Option<Resemblance>,
    /// Why it was not looked at (its slicing failed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The time its slicing took, and the visible lines of its G-code.
    pub slice_s: f64,
    pub lines: usize,
}

/// Why the strength is what it is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Choice {
    /// The candidate the observer found most like the reference (the first of equals).
    #[default]
    MostAlike,
    /// Printed at or above the reference size: unmodified, as the table prints it there.
    AtReference,
    /// The time bound passed before every candidate was seen: the paper's table.
    TimedOut,
    /// The reference could not be made or seen, or no candidate could: the paper's table.
    Failed,
}

/// The picture of the views, in `--pictures` and in a job's directory.
pub const OBSERVED_PNG: &str = "observed.png";
