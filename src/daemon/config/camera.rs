//! `[camera]` (how frames are fetched, kept and turned into timelapses) and each printer's
//! `[printer.camera]` (where its frames come from, the way camera servers publish them,
//! and how its picture is cut and turned). A camera that serves several printers (a shelf
//! view) is named by the same URL on each, with a crop per printer: it is fetched once.

use super::check::{number, seconds_in, Bounds};
/// A camera's URL is read as a notification receiver's is.
use crate::outbound::HttpUrl;
use serde::Deserialize;
use std::time::Duration;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawCamera {
    pub(super) refresh_s: Option<f64>,
    pub(super) timeout_s: Option<f64>,
    pub(super) frame_max_mb: Option<f64>,
    pub(super) frozen_after_s: Option<f64>,
    /// "layers", "off", or a number of seconds between frames.
    pub(super) timelapse: Option<toml::Value>,
    pub(super) disk_limit_mb: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawPrinterCamera {
    /// A URL that answers one JPEG (ustreamer's and mjpg-streamer's `/snapshot`,
    /// `?action=snapshot`).
    pub(super) snapshot: Option<String>,
    /// An MJPEG stream (`multipart/x-mixed-replace`, `?action=stream`).
    pub(super) stream: Option<String>,
    /// `[x, y, width, height]` in the camera's pixels.
    pub(super) crop: Option<Vec<i64>>,
    pub(super) flip_horizontal: Option<bool>,
    pub(super) flip_vertical: Option<bool>,
    /// Clockwise degrees: 0, 90, 180 or 270.
    pub(super) rotate: Option<i64>,
    /// `[x, y, width, height]` of the bed in the printer's picture (after the crop and
    /// turns), for the bed check; default: the whole picture.
    pub(super) bed_region: Option<Vec<i64>>,
}

/// `[camera]`, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraSettings {
    /// A camera is asked for a frame this often (a stream's frames are kept at this pace).
    pub refresh: Duration,
    /// The longest a camera may take to answer or to send the next frame.
    pub timeout: Duration,
    /// The largest frame taken.
    pub frame_max_bytes: usize,
    /// The same picture this long while its printer prints: the camera is frozen.
    pub frozen_after: Duration,
    pub timelapse: Timelapse,
    /// Snapshots and timelapses of all jobs together; the oldest jobs' go first, never the
    /// current job's.
    pub disk_limit_bytes: u64,
}

impl Default for CameraSettings {
    fn default() -> Self {
        CameraSettings {
            refresh: Duration::from_secs(5),
            timeout: Duration::from_secs(5),
            frame_max_bytes: 8 << 20,
            frozen_after: Duration::from_secs(600),
            timelapse: Timelapse::Layers,
            disk_limit_bytes: 2048 << 20,
        }
    }
}

/// When a timelapse takes its frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Timelapse {
    Off,
    /// One frame at each layer change of the G-code being printed.
    Layers,
    /// One frame this often.
    Every(Duration),
}

/// Where a camera's frames come from.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraSource {
    Snapshot(HttpUrl),
    Stream(HttpUrl),
}

impl CameraSource {
    pub fn url(&self) -> &HttpUrl {
        match self {
            CameraSource::Snapshot(u) | CameraSource::Stream(u) => u,
        }
    }
}

/// How a printer's picture is made from its camera's frame, in this order: crop, flips,
/// rotation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CameraTransform {
    pub crop: Option<[u32; 4]>,
    pub flip_horizontal: bool,
    pub flip_vertical: bool,
    /// Clockwise quarter turns (0 to 3).
    pub quarter_turns: u8,
}

impl CameraTransform {
    pub fn is_identity(&self) -> bool {
        *self == CameraTransform::default()
    }
}

/// `[printer.camera]`, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct PrinterCamera {
    pub source: CameraSource,
    pub transform: CameraTransform,
    /// The bed's region in the printer's picture (None: all of it), for the bed check.
    pub bed_region: Option<crate::bedcheck::Region>,
}

const REFRESH_S: Bounds = 1.0..=3600.0;
const TIMEOUT_S: Bounds = 0.5..=60.0;
const FRAME_MAX_MB: Bounds = 0.1..=64.0;
const FROZEN_AFTER_S: Bounds = 30.0..=86_400.0;
const TIMELAPSE_EVERY_S: Bounds = 1.0..=3600.0;
const DISK_LIMIT_MB: Bounds = 10.0..=10_000_000.0;
/// The largest crop edge taken: past any camera's sensor.
const MAX_CROP_EDGE: i64 = 16_384;

/// Checks `[camera]`; the error names the key.
pub(super) fn check(raw: Option<RawCamera>) -> Result<CameraSettings, (&'static str, String)> {
    let mut s = CameraSettings::default();
    let Some(raw) = raw else {
        return Ok(s);
    };
    if let Some(v) = raw.refresh_s {
        s.refresh = seconds_in(v, &REFRESH_S).map_err(|m| ("refresh_s", m))?;
    }
    if let Some(v) = raw.timeout_s {
        s.timeout = seconds_in(v, &TIMEOUT_S).map_err(|m| ("timeout_s", m))?;
    }
    if let Some(v) = raw.frozen_after_s {
        s.frozen_after = seconds_in(v, &FROZEN_AFTER_S).map_err(|m| ("frozen_after_s", m))?;
    }
    if let Some(mb) = raw.frame_max_mb {
        s.frame_max_bytes = megabytes(mb, &FRAME_MAX_MB).map_err(|m| ("frame_max_mb", m))? as usize;
    }
    if let Some(mb) = raw.disk_limit_mb {
        s.disk_limit_bytes = megabytes(mb, &DISK_LIMIT_MB).map_err(|m| ("disk_limit_mb", m))?;
    }
    if let Some(v) = raw.timelapse {
        s.timelapse = match v {
            toml::Value::String(w) if w == "layers" => Timelapse::Layers,
            toml::Value::String(w) if w == "off" => Timelapse::Off,
            toml::Value::Integer(n) => Timelapse::Every(
                seconds_in(n as f64, &TIMELAPSE_EVERY_S).map_err(|m| ("timelapse", m))?,
            ),
            toml::Value::Float(n) => Timelapse::Every(
                seconds_in(n, &TIMELAPSE_EVERY_S).map_err(|m| ("timelapse", m))?,
            ),
            other => {
                return Err((
                    "timelapse",
                    format!(
                        "must be \"layers\" (a frame per layer), \"off\", or seconds between frames, got {other}"
                    ),
                ))
            }
        };
    }
    Ok(s)
}

fn megabytes(mb: f64, range: &Bounds) -> Result<u64, String> {
    if mb.is_finite() && range.contains(&mb) {
        Ok((mb * 1024.0 * 1024.0) as u64)
    } else {
        Err(format!(
            "must be from {} to {} MB, got {}",
            range.start(),
            range.end(),
            number(mb)
        ))
    }
}

/// Checks a `[printer.camera]` table; the error names the key.
pub(super) fn check_printer(
    raw: RawPrinterCamera,
) -> Result<PrinterCamera, (&'static str, String)> {
    let source = match (raw.snapshot, raw.stream) {
        (Some(u), None) => CameraSource::Snapshot(HttpUrl::parse(&u).map_err(|m| ("snapshot", m))?),
        (None, Some(u)) => CameraSource::Stream(HttpUrl::parse(&u).map_err(|m| ("stream", m))?),
        (Some(_), Some(_)) => return Err((
            "stream",
            "give `snapshot` (a URL answering one JPEG) or `stream` (an MJPEG stream), not both"
                .into(),
        )),
        (None, None) => {
            return Err((
                "snapshot",
                "missing: give `snapshot` (e.g. \"http://127.0.0.1:8080/snapshot\") or `stream` \
                 (e.g. \"http://127.0.0.1:8080/?action=stream\")"
                    .into(),
            ))
        }
    };
    let rectangle = |key: &'static str, c: Option<Vec<i64>>, whose: &str| match c {
        None => Ok(None),
        Some(c) => {
            let ok = c.len() == 4
                && c[..2].iter().all(|v| (0..MAX_CROP_EDGE).contains(v))
                && c[2..].iter().all(|v| (1..=MAX_CROP_EDGE).contains(v));
            if !ok {
                return Err((
                    key,
                    format!(
                        "must be [x, y, width, height] in {whose} pixels (x, y from 0, width and height from 1, each below {MAX_CROP_EDGE}), got {c:?}"
                    ),
                ));
            }
            Ok(Some([c[0] as u32, c[1] as u32, c[2] as u32, c[3] as u32]))
        }
    };
    let crop = rectangle("crop", raw.crop, "the camera's")?;
    let bed_region = rectangle("bed_region", raw.bed_region, "the printer's picture's")?
        .map(|[x, y, w, h]| crate::bedcheck::Region { x, y, w, h });
    let quarter_turns = match raw.rotate.unwrap_or(0) {
        0 => 0,
        90 => 1,
        180 => 2,
        270 => 3,
        other => {
            return Err((
                "rotate",
                format!("must be 0, 90, 180 or 270 (degrees clockwise), got {other}"),
            ))
        }
    };
    Ok(PrinterCamera {
        source,
        transform: CameraTransform {
            crop,
            flip_horizontal: raw.flip_horizontal.unwrap_or(false),
            flip_vertical: raw.flip_vertical.unwrap_or(false),
            quarter_turns,
        },
        bed_region,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(text: &str) -> Result<PrinterCamera, (&'static str, String)> {
        check_printer(toml::from_str(text).unwrap())
    }

    #[test]
    fn a_printer_camera_is_one_source_with_a_bounded_transform() {
        let c = camera(
            "stream = \"http://cam:8080/?action=stream\"\ncrop = [10, 20, 320, 240]\nrotate = 90\nflip_vertical = true",
        )
        .unwrap();
        assert_eq!(c.source.url().path, "/?action=stream");
        assert!(matches!(c.source, CameraSource::Stream(_)));
        assert_eq!(c.transform.crop, Some([10, 20, 320, 240]));
        assert_eq!(c.transform.quarter_turns, 1);
        assert!(c.transform.flip_vertical && !c.transform.flip_horizontal);
        for (text, key) in [
            ("", "snapshot"),
            (
                "snapshot = \"http://a/s\"\nstream = \"http://a/t\"",
                "stream",
            ),
            ("snapshot = \"ftp://a/s\"", "snapshot"),
            ("snapshot = \"http://a/s\"\ncrop = [0, 0, 0, 10]", "crop"),
            ("snapshot = \"http://a/s\"\ncrop = [0, 0, 10]", "crop"),
            ("snapshot = \"http://a/s\"\ncrop = [-1, 0, 10, 10]", "crop"),
            ("snapshot = \"http://a/s\"\nrotate = 45", "rotate"),
        ] {
            assert_eq!(camera(text).unwrap_err().0, key, "{text}");
        }
        assert!(toml::from_str::<RawPrinterCamera>("url = \"http://a\"").is_err());
    }

    #[test]
    fn camera_settings_are_bounded() {
        let parse = |text: &str| check(Some(toml::from_str(text).unwrap()));
        assert_eq!(check(None).unwrap(), CameraSettings::default());
        let s = parse("timelapse = 10\nrefresh_s = 2\ndisk_limit_mb = 100").unwrap();
        assert_eq!(s.timelapse, Timelapse::Every(Duration::from_secs(10)));
        assert_eq!(s.refresh, Duration::from_secs(2));
        assert_eq!(s.disk_limit_bytes, 100 << 20);
        assert_eq!(
            parse("timelapse = \"off\"").unwrap().timelapse,
            Timelapse::Off
        );
        for (text, key) in [
            ("timelapse = \"sometimes\"", "timelapse"),
            ("timelapse = 0", "timelapse"),
            ("refresh_s = 0.1", "refresh_s"),
            ("timeout_s = nan", "timeout_s"),
            ("frame_max_mb = 1000", "frame_max_mb"),
            ("disk_limit_mb = 1", "disk_limit_mb"),
            ("frozen_after_s = 1", "frozen_after_s"),
        ] {
            assert_eq!(parse(text).unwrap_err().0, key, "{text}");
        }
    }
}
