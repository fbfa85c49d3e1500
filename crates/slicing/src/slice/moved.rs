//! What the enhancement moved, as the figures of one line an operator reads: how much of
//! the print moves by more than a printer draws (a quarter of the line width,
//! `crispen_geometry::enhance::printed`), on how much of it, and how far all but 1 % of it
//! moves, in mm (the largest move of a wall is often a contour that a tiny change in Z
//! moved far, not what a viewer sees).
//!
//! The outer walls of the G-code ([`WallComparison`](super::walls::WallComparison)) are what a viewer sees of the
//! print, so they are said when measured; until then (the daemon measures them after the
//! job is ready) the enhanced mesh's figures at the printed size stand in
//! ([`PrintedDisplacement`](crispen_geometry::enhance::PrintedDisplacement)), and the line says so. A report keeps only its figures and
//! where its walls stand ([`SliceReport::walls_state`]); [`SliceReport::moved`] picks the
//! figures ([`Moved`]), and the words are made where they are shown (its `Display`), so
//! every reader (job page, `crispen slice`, `crispen status`, the history) says the same.

use super::SliceReport;
use serde::{Deserialize, Serialize};
use std::fmt;

/// The enhancement's mode of a job whose G-code was sliced elsewhere.
pub const PRESLICED: &str = "pre-sliced";

pub use super::WallsState;

/// What the enhancement moved: the figures its one line says. A distance or share that is
/// not a finite number is `None` ("an unknown distance"), so the figures always read back.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "from", rename_all = "snake_case")]
pub enum Moved {
    /// Sliced elsewhere: crispen moved nothing.
    Presliced,
    /// Printed unmodified.
    Unmodified,
    /// The outer walls of the enhanced and the unmodified G-code, compared.
    Walls {
        /// Layers compared; none means the two share no layer.
        layers: usize,
        /// The limit a move is counted past: a quarter line width, or 0.1 mm in reports
        /// made before the quarter line was measured (`quarter_line` false).
        limit_mm: Option<f64>,
        quarter_line: bool,
        /// The share of the wall's length moved past the limit.
        share: Option<f64>,
        p99_mm: Option<f64>,
        max_mm: Option<f64>,
    },
    /// The enhanced mesh at the printed size, standing in while the walls are not
    /// measured (`walls` says why).
    Mesh {
        /// A quarter line width, when the machine is known (else no share either).
        limit_mm: Option<f64>,
        /// The share of the surface's area moved past the limit.
        share: Option<f64>,
        p99_mm: Option<f64>,
        max_mm: Option<f64>,
        walls: WallsState,
    },
    /// Enhanced, with neither the walls nor the mesh measured.
    Unmeasured { walls: WallsState },
}

impl SliceReport {
    /// What the enhancement moved, from the report's figures.
    pub fn moved(&self) -> Moved {
        let e = &self.enhancement;
        if e.lambda2.is_none() {
            return if e.mode == PRESLICED {
                Moved::Presliced
            } else {
                Moved::Unmodified
            };
        }
        if let Some(w) = &self.walls {
            // Reports made before `quarter_line_mm` was measured have it 0: their 0.1 mm
            // share (a quarter of the common 0.4 mm line) is said instead.
            let quarter_line = w.quarter_line_mm > 0.0;
            return Moved::Walls {
                layers: w.layers,
                limit_mm: finite(if quarter_line { w.quarter_line_mm } else { 0.1 }),
                quarter_line,
                share: finite(if quarter_line {
                    w.share_over_quarter_line
                } else {
                    w.share_over_0_1_mm
                }),
                p99_mm: finite(w.p99_mm),
                max_mm: finite(w.max_mm),
            };
        }
        let walls = self.walls_state;
        match &e.printed {
            Some(p) => Moved::Mesh {
                limit_mm: p.threshold_mm.and_then(finite),
                share: p.threshold_mm.and(p.share_above_threshold).and_then(finite),
                p99_mm: finite(p.p99_mm),
                max_mm: finite(p.max_mm),
                walls,
            },
            None => Moved::Unmeasured { walls },
        }
    }
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// The one line (see the module's comment).
impl fmt::Display for Moved {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let source = |walls: &WallsState| match walls {
            WallsState::NotAsked => "the outer walls in the G-code were not compared",
            WallsState::Pending => "the outer walls in the G-code are still to be compared",
            WallsState::NotMeasured => "the outer walls in the G-code could not be compared",
        };
        match self {
            Moved::Presliced => f.write_str("Sliced elsewhere: crispen moved nothing."),
            Moved::Unmodified => f.write_str("Printed unmodified: the enhancement moved nothing."),
            Moved::Walls { layers: 0, .. } => f.write_str(
                "The outer walls of the enhanced and the unmodified G-code share no layer: \
                 nothing to compare.",
            ),
            Moved::Walls {
                limit_mm,
                quarter_line,
                share,
                p99_mm,
                max_mm,
                ..
            } => {
                let limit = if *quarter_line {
                    Limit::QuarterLine(*limit_mm)
                } else {
                    Limit::Fixed(*limit_mm)
                };
                let reach = reach(*p99_mm, *max_mm);
                write!(
                    f,
                    "{}.",
                    share_line("The outer wall", limit, *share, "length", reach)
                )
            }
            Moved::Mesh {
                limit_mm,
                share,
                p99_mm,
                max_mm,
                walls,
            } => {
                let reach = reach(*p99_mm, *max_mm);
                let line = match limit_mm {
                    Some(t) => share_line(
                        "The surface",
                        Limit::QuarterLine(Some(*t)),
                        *share,
                        "area",
                        reach,
                    ),
                    None => format!("The surface moves {reach}"),
                };
                write!(
                    f,
                    "{line} (from the enhanced mesh at the printed size; {}).",
                    source(walls)
                )
            }
            Moved::Unmeasured { walls } => write!(
                f,
                "Enhanced; how far the surface moved was not measured, and {}.",
                source(walls)
            ),
        }
    }
}

/// How far the moves go: all but 1 % of them, or the largest where a report from before
/// the 99th percentile was kept has only that.
fn reach(p99_mm: Option<f64>, max_mm: Option<f64>) -> Reach {
    if p99_mm.is_some_and(|v| v > 0.0) || max_mm == Some(0.0) {
        Reach::P99(p99_mm)
    } else {
        Reach::Max(max_mm)
    }
}

#[derive(Clone, Copy)]
enum Reach {
    P99(Option<f64>),
    Max(Option<f64>),
}

impl fmt::Display for Reach {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Reach::P99(v) => write!(f, "at most {} on 99 % of it", mm(v)),
            Reach::Max(v) => write!(f, "at most {}", mm(v)),
        }
    }
}

#[derive(Clone, Copy)]
enum Limit {
    QuarterLine(Option<f64>),
    Fixed(Option<f64>),
}

/// "`what` moves by more than `limit` on `share` of its `extent`; `reach`".
fn share_line(what: &str, limit: Limit, share: Option<f64>, extent: &str, reach: Reach) -> String {
    let limit = match limit {
        Limit::QuarterLine(t) => format!("a quarter line width ({})", mm(t)),
        Limit::Fixed(t) => mm(t),
    };
    match share {
        None => format!("{what} moves {reach}"),
        Some(s) if s <= 0.0 => {
            format!("{what} moves by no more than {limit} anywhere; {reach}")
        }
        Some(s) if s >= 1.0 => {
            format!("{what} moves by more than {limit} on all of its {extent}; {reach}")
        }
        Some(s) => format!(
            "{what} moves by more than {limit} on {} of its {extent}; {reach}",
            percent(s)
        ),
    }
}

/// A share strictly between 0 and 1 as a percentage that never reads as 0 % or 100 %.
fn percent(share: f64) -> String {
    let p = 100.0 * share;
    if p < 0.1 {
        "less than 0.1 %".into()
    } else if p < 9.95 {
        // One decimal below 10 %, where a whole percent would hide the difference.
        format!("{} %", trim(format!("{p:.1}")))
    } else if p > 99.0 {
        "more than 99 %".into()
    } else {
        format!("{p:.0} %")
    }
}

/// A distance to a hundredth of a mm, a thousandth below 0.1 mm.
fn mm(v: Option<f64>) -> String {
    let v = match v {
        Some(v) if v >= 0.0 => v,
        _ => return "an unknown distance".into(),
    };
    if v == 0.0 {
        "0 mm".into()
    } else if v < 0.0005 {
        "less than 0.001 mm".into()
    } else if v < 0.0995 {
        format!("{} mm", trim(format!("{v:.3}")))
    } else {
        format!("{} mm", trim(format!("{v:.2}")))
    }
}

/// "0.10" → "0.1", "2.00" → "2".
fn trim(s: String) -> String {
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::slice::walls::WallComparison;
    use crate::slice::EnhancementSummary;
    use crispen_geometry::enhance::PrintedDisplacement;

    /// The line a report with these figures says.
    fn said(
        enhancement: &EnhancementSummary,
        walls: Option<&WallComparison>,
        walls_state: WallsState,
    ) -> String {
        let report = SliceReport {
            enhancement: enhancement.clone(),
            walls: walls.cloned(),
            walls_state,
            ..SliceReport::default()
        };
        report.moved().to_string()
    }

    fn enhanced(printed: Option<PrintedDisplacement>) -> EnhancementSummary {
        EnhancementSummary {
            lambda2: Some(0.8),
            mode: "enhanced".into(),
            printed,
            ..EnhancementSummary::default()
        }
    }

    /// Walls whose largest move is a far contour (5 mm), unless nothing moved.
    fn walls(share: f64, p99_mm: f64) -> WallComparison {
        WallComparison {
            layers: 40,
            quarter_line_mm: 0.1,
            share_over_quarter_line: share,
            p99_mm,
            max_mm: if p99_mm > 0.0 { 5.0 } else { 0.0 },
            ..WallComparison::default()
        }
    }

    fn printed(share: Option<f64>, p99_mm: f64) -> PrintedDisplacement {
        PrintedDisplacement {
            p99_mm,
            max_mm: 1.5 * p99_mm,
            threshold_mm: share.map(|_| 0.1),
            share_above_threshold: share,
            ..PrintedDisplacement::default()
        }
    }

    fn line(w: WallComparison) -> String {
        said(&enhanced(None), Some(&w), WallsState::Pending)
    }

    #[test]
    fn the_walls_are_said_in_mm_and_percent_rounded() {
        assert_eq!(
            line(walls(0.2149, 0.1849)),
            "The outer wall moves by more than a quarter line width (0.1 mm) on 21 % of its \
             length; at most 0.18 mm on 99 % of it."
        );
        assert!(line(walls(0.2151, 0.18)).contains("on 22 % of"));
        // Below 10 %, one decimal; a share never reads as 0 % or 100 %.
        assert!(line(walls(0.0349, 0.2)).contains("on 3.5 % of"));
        assert!(line(walls(0.05, 0.2)).contains("on 5 % of"));
        assert!(line(walls(0.0004, 0.2)).contains("on less than 0.1 % of"));
        assert!(line(walls(0.9951, 0.2)).contains("on more than 99 % of"));
        assert!(line(walls(0.99, 0.2)).contains("on 99 % of"));
    }

    #[test]
    fn none_and_all_of_the_wall_are_said_in_words() {
        assert_eq!(
            line(walls(0.0, 0.06)),
            "The outer wall moves by no more than a quarter line width (0.1 mm) anywhere; at \
             most 0.06 mm on 99 % of it."
        );
        assert_eq!(
            line(walls(1.0, 1.5)),
            "The outer wall moves by more than a quarter line width (0.1 mm) on all of its \
             length; at most 1.5 mm on 99 % of it."
        );
        // A share past 1 (never made, but read from a file) is all of it.
        assert!(line(walls(1.7, 1.5)).contains("on all of its length"));
    }

    #[test]
    fn tiny_and_broken_numbers_are_said_without_a_false_zero() {
        assert!(line(walls(0.0, 0.0)).ends_with("at most 0 mm on 99 % of it."));
        assert!(line(walls(0.0, 0.0003)).ends_with("at most less than 0.001 mm on 99 % of it."));
        assert!(line(walls(0.0, 0.0123)).ends_with("at most 0.012 mm on 99 % of it."));
        assert!(line(walls(0.0, 0.0996)).ends_with("at most 0.1 mm on 99 % of it."));
        assert!(line(walls(0.5, f64::NAN)).ends_with("at most an unknown distance on 99 % of it."));
        // A share that is not a number says only the largest move.
        assert_eq!(
            line(walls(f64::NAN, 0.2)),
            "The outer wall moves at most 0.2 mm on 99 % of it."
        );
        let mut w = walls(0.5, 0.2);
        // A 0.25 mm nozzle's quarter line, to the thousandth (an exact tie rounds to even).
        w.quarter_line_mm = 0.0625;
        assert!(line(w).contains("a quarter line width (0.062 mm)"));
    }

    #[test]
    fn a_report_from_before_the_quarter_line_says_its_0_1_mm_share() {
        let w = WallComparison {
            layers: 3,
            share_over_0_1_mm: 0.3,
            max_mm: 0.25,
            ..WallComparison::default()
        };
        assert_eq!(
            line(w),
            "The outer wall moves by more than 0.1 mm on 30 % of its length; at most 0.25 mm."
        );
        let none = WallComparison::default();
        assert!(line(none).contains("share no layer"));
    }

    #[test]
    fn without_walls_the_mesh_stands_in_and_says_so() {
        let e = enhanced(Some(printed(Some(0.4), 0.31)));
        assert_eq!(
            said(&e, None, WallsState::Pending),
            "The surface moves by more than a quarter line width (0.1 mm) on 40 % of its area; \
             at most 0.31 mm on 99 % of it (from the enhanced mesh at the printed size; the outer walls in \
             the G-code are still to be compared)."
        );
        assert!(said(&e, None, WallsState::NotMeasured).ends_with("could not be compared)."));
        assert!(said(&e, None, WallsState::NotAsked).ends_with("were not compared)."));
        // Without a machine the share is not known.
        let e = enhanced(Some(printed(None, 0.31)));
        assert!(said(&e, None, WallsState::NotAsked)
            .starts_with("The surface moves at most 0.31 mm on 99 % of it (from the enhanced"));
        let e = enhanced(None);
        assert_eq!(
            said(&e, None, WallsState::Pending),
            "Enhanced; how far the surface moved was not measured, and the outer walls in the \
             G-code are still to be compared."
        );
    }

    #[test]
    fn an_unmodified_print_moved_nothing() {
        let plain = EnhancementSummary {
            mode: "unmodified".into(),
            ..EnhancementSummary::default()
        };
        let words = said(&plain, None, WallsState::NotAsked);
        assert_eq!(words, "Printed unmodified: the enhancement moved nothing.");
        assert_eq!(
            said(&plain, Some(&walls(0.5, 1.0)), WallsState::Pending),
            words
        );
        let presliced = EnhancementSummary {
            mode: PRESLICED.into(),
            ..EnhancementSummary::default()
        };
        let words = said(&presliced, None, WallsState::NotAsked);
        assert_eq!(words, "Sliced elsewhere: crispen moved nothing.");
    }

    #[test]
    fn a_report_says_its_walls_once_measured() {
        let mut r = SliceReport {
            enhancement: enhanced(Some(printed(Some(0.4), 0.31))),
            walls_state: WallsState::Pending,
            ..SliceReport::default()
        };
        assert!(r.moved().to_string().contains("still to be compared"));
        r.walls = Some(walls(0.21, 0.18));
        assert!(r.moved().to_string().starts_with("The outer wall moves"));
    }

    /// Figures that are not numbers are kept as unknown, so a record holding them (the
    /// history's) reads back, and says the same.
    #[test]
    fn the_figures_read_back_whatever_they_hold() {
        for (w, state) in [
            (Some(walls(f64::NAN, f64::INFINITY)), WallsState::Pending),
            (Some(walls(0.3, 0.2)), WallsState::NotAsked),
            (None, WallsState::NotMeasured),
        ] {
            let e = enhanced(Some(printed(Some(f64::NAN), f64::NAN)));
            let r = SliceReport {
                enhancement: e,
                walls: w,
                walls_state: state,
                ..SliceReport::default()
            };
            let figures = r.moved();
            let json = serde_json::to_string(&figures).unwrap();
            let back: Moved = serde_json::from_str(&json).unwrap();
            assert_eq!(back, figures, "{json}");
            assert_eq!(back.to_string(), figures.to_string());
        }
    }
}
