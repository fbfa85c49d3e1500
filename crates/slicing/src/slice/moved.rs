//! What the enhancement moved, in one line an operator reads: how much of the print moves
//! by more than a printer draws (a quarter of the line width, `crispen_geometry::enhance::printed`),
//! on how much of it, and how far all but 1 % of it moves, in mm (the largest move of a
//! wall is often a contour that a tiny change in Z moved far, not what a viewer sees).
//!
//! The outer walls of the G-code ([`WallComparison`]) are what a viewer sees of the
//! print, so they are said when measured; until then (the daemon measures them after the
//! job is ready) the enhanced mesh's figures at the printed size stand in
//! ([`PrintedDisplacement`]), and the line says so. The line is made once, when a report
//! is made or its comparison recorded ([`SliceReport::set_moved`]), and kept in the
//! report, so every reader (job page, `crispen slice`, `crispen status`, the history) says
//! the same.

use super::walls::WallComparison;
use super::{EnhancementSummary, SliceReport};
use crispen_geometry::enhance::PrintedDisplacement;

/// The enhancement's mode of a job whose G-code was sliced elsewhere.
pub const PRESLICED: &str = "pre-sliced";

/// Where the comparison of the outer walls stands when a report has none.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WallsState {
    /// Not asked for (`crispen slice` without `--compare`).
    NotAsked,
    /// To be measured (the daemon's, after the job is ready).
    Pending,
    /// Asked for and not made (the reason is the comparison's own, shown beside it).
    NotMeasured,
}

impl SliceReport {
    /// Makes the report's `moved` line from its figures, the walls' standing as `state`
    /// when it has no wall figures.
    pub fn set_moved(&mut self, state: WallsState) {
        self.moved = Some(moved(&self.enhancement, self.walls.as_ref(), state));
    }
}

/// The one line saying what the enhancement moved (see the module's comment).
pub fn moved(
    enhancement: &EnhancementSummary,
    walls: Option<&WallComparison>,
    state: WallsState,
) -> String {
    if enhancement.lambda2.is_none() {
        return if enhancement.mode == PRESLICED {
            "Sliced elsewhere: crispen moved nothing.".into()
        } else {
            "Printed unmodified: the enhancement moved nothing.".into()
        };
    }
    if let Some(w) = walls {
        return walls_line(w);
    }
    let source = match state {
        WallsState::NotAsked => "the outer walls in the G-code were not compared",
        WallsState::Pending => "the outer walls in the G-code are still to be compared",
        WallsState::NotMeasured => "the outer walls in the G-code could not be compared",
    };
    match &enhancement.printed {
        Some(p) => format!(
            "{} (from the enhanced mesh at the printed size; {source}).",
            mesh_line(p)
        ),
        None => format!("Enhanced; how far the surface moved was not measured, and {source}."),
    }
}

/// The outer wall's figures. Reports made before `quarter_line_mm` was measured have it
/// 0: their 0.1 mm share (a quarter of the common 0.4 mm line) is said instead.
fn walls_line(w: &WallComparison) -> String {
    if w.layers == 0 {
        return "The outer walls of the enhanced and the unmodified G-code share no layer: \
                nothing to compare."
            .into();
    }
    let limit = if w.quarter_line_mm > 0.0 {
        Limit::QuarterLine(w.quarter_line_mm)
    } else {
        Limit::Fixed(0.1)
    };
    let share = match limit {
        Limit::QuarterLine(_) => w.share_over_quarter_line,
        Limit::Fixed(_) => w.share_over_0_1_mm,
    };
    share_line(
        "The outer wall",
        limit,
        Some(share),
        "length",
        reach(w.p99_mm, w.max_mm),
    ) + "."
}

/// How far the moves go: all but 1 % of them, or the largest where a report from before
/// the 99th percentile was kept has only that.
fn reach(p99_mm: f64, max_mm: f64) -> Reach {
    if p99_mm > 0.0 || max_mm == 0.0 {
        Reach::P99(p99_mm)
    } else {
        Reach::Max(max_mm)
    }
}

#[derive(Clone, Copy)]
enum Reach {
    P99(f64),
    Max(f64),
}

impl std::fmt::Display for Reach {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Reach::P99(v) => write!(f, "at most {} on 99 % of it", mm(v)),
            Reach::Max(v) => write!(f, "at most {}", mm(v)),
        }
    }
}

/// The mesh's figures (without a machine, its share is not known: only its largest move).
fn mesh_line(p: &PrintedDisplacement) -> String {
    match p.threshold_mm {
        Some(t) => share_line(
            "The surface",
            Limit::QuarterLine(t),
            p.share_above_threshold,
            "area",
            reach(p.p99_mm, p.max_mm),
        ),
        None => format!("The surface moves {}", reach(p.p99_mm, p.max_mm)),
    }
}

#[derive(Clone, Copy)]
enum Limit {
    QuarterLine(f64),
    Fixed(f64),
}

/// "`what` moves by more than `limit` on `share` of its `extent`; `reach`".
fn share_line(what: &str, limit: Limit, share: Option<f64>, extent: &str, reach: Reach) -> String {
    let limit = match limit {
        Limit::QuarterLine(t) => format!("a quarter line width ({})", mm(t)),
        Limit::Fixed(t) => mm(t),
    };
    match share.filter(|s| s.is_finite()) {
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
fn mm(v: f64) -> String {
    if !v.is_finite() || v < 0.0 {
        return "an unknown distance".into();
    }
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
        moved(&enhanced(None), Some(&w), WallsState::Pending)
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
            moved(&e, None, WallsState::Pending),
            "The surface moves by more than a quarter line width (0.1 mm) on 40 % of its area; \
             at most 0.31 mm on 99 % of it (from the enhanced mesh at the printed size; the outer walls in \
             the G-code are still to be compared)."
        );
        assert!(moved(&e, None, WallsState::NotMeasured).ends_with("could not be compared)."));
        assert!(moved(&e, None, WallsState::NotAsked).ends_with("were not compared)."));
        // Without a machine the share is not known.
        let e = enhanced(Some(printed(None, 0.31)));
        assert!(moved(&e, None, WallsState::NotAsked)
            .starts_with("The surface moves at most 0.31 mm on 99 % of it (from the enhanced"));
        let e = enhanced(None);
        assert_eq!(
            moved(&e, None, WallsState::Pending),
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
        let said = moved(&plain, None, WallsState::NotAsked);
        assert_eq!(said, "Printed unmodified: the enhancement moved nothing.");
        assert_eq!(
            moved(&plain, Some(&walls(0.5, 1.0)), WallsState::Pending),
            said
        );
        let presliced = EnhancementSummary {
            mode: PRESLICED.into(),
            ..EnhancementSummary::default()
        };
        let said = moved(&presliced, None, WallsState::NotAsked);
        assert_eq!(said, "Sliced elsewhere: crispen moved nothing.");
    }

    #[test]
    fn a_report_keeps_its_line() {
        let mut r = SliceReport {
            enhancement: enhanced(Some(printed(Some(0.4), 0.31))),
            ..SliceReport::default()
        };
        r.set_moved(WallsState::Pending);
        assert!(r.moved.as_deref().unwrap().contains("still to be compared"));
        r.walls = Some(walls(0.21, 0.18));
        r.set_moved(WallsState::Pending);
        assert!(r
            .moved
            .as_deref()
            .unwrap()
            .starts_with("The outer wall moves"));
    }
}
