//! The slicer settings a farm varies per folder or per job ([`SliceSettings`]), their
//! bounds for an Ultimaker 2 with a 0.4 mm nozzle, and the material presets.

use super::SliceError;
use serde::{Deserialize, Serialize};

/// Settings a farm varies per folder or per job, on top of the profile. `None` keeps the
/// profile's value (temperatures: the material preset's).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SliceSettings {
    pub layer_height_mm: Option<f64>,
    pub infill_percent: Option<f64>,
    pub supports: Option<bool>,
    pub nozzle_temp_c: Option<f64>,
    pub bed_temp_c: Option<f64>,
    /// A material preset: `pla` (default), `petg`, `abs` or `tpu`; sets temperatures and
    /// density.
    pub material: Option<String>,
}

/// The keys `SliceSettings::set` accepts (`crispen slice --set KEY=VALUE`).
pub const SETTING_KEYS: &[&str] = &[
    "layer_height",
    "infill",
    "supports",
    "nozzle_temp",
    "bed_temp",
    "material",
];

/// A material preset: temperatures and density (for grams of filament).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Material {
    pub name: &'static str,
    pub nozzle_temp_c: f64,
    pub bed_temp_c: f64,
    pub density_g_cm3: f64,
    /// The hotend temperatures it prints between, °C: the G-code policy refuses a file
    /// for it that heats beyond.
    pub nozzle_range_c: [f64; 2],
    pub bed_range_c: [f64; 2],
}

/// Density of a material by name (a preset's; PLA's for one crispen has no preset of).
pub fn density_of(material: &str) -> f64 {
    MATERIALS
        .iter()
        .find(|m| m.name.eq_ignore_ascii_case(material.trim()))
        .unwrap_or(&MATERIALS[0])
        .density_g_cm3
}

/// Presets from PrusaSlicer's Ultimaker 2 filament profiles.
pub const MATERIALS: &[Material] = &[
    Material {
        name: "pla",
        nozzle_temp_c: 210.0,
        bed_temp_c: 60.0,
        density_g_cm3: 1.24,
        nozzle_range_c: [180.0, 230.0],
        bed_range_c: [0.0, 70.0],
    },
    Material {
        name: "petg",
        nozzle_temp_c: 235.0,
        bed_temp_c: 85.0,
        density_g_cm3: 1.27,
        nozzle_range_c: [220.0, 255.0],
        bed_range_c: [60.0, 95.0],
    },
    Material {
        name: "abs",
        nozzle_temp_c: 240.0,
        bed_temp_c: 80.0,
        density_g_cm3: 1.10,
        nozzle_range_c: [220.0, 260.0],
        bed_range_c: [70.0, 110.0],
    },
    // Flexible: slower and cooler; from the TPU 95A data sheets of the common brands.
    Material {
        name: "tpu",
        nozzle_temp_c: 225.0,
        bed_temp_c: 50.0,
        density_g_cm3: 1.21,
        nozzle_range_c: [210.0, 240.0],
        bed_range_c: [0.0, 65.0],
    },
];

impl SliceSettings {
    /// `self` with every setting `over` gives replaced (folder settings, then job settings).
    pub fn merge(&self, over: &SliceSettings) -> SliceSettings {
        SliceSettings {
            layer_height_mm: over.layer_height_mm.or(self.layer_height_mm),
            infill_percent: over.infill_percent.or(self.infill_percent),
            supports: over.supports.or(self.supports),
            nozzle_temp_c: over.nozzle_temp_c.or(self.nozzle_temp_c),
            bed_temp_c: over.bed_temp_c.or(self.bed_temp_c),
            material: over.material.clone().or_else(|| self.material.clone()),
        }
    }

    /// Sets one setting from text, as given on the command line (`infill=15`).
    /// Nothing changes when the value is refused.
    pub fn set(&mut self, key: &str, value: &str) -> Result<(), SliceError> {
        let mut changed = self.clone();
        changed.set_unchecked(key, value)?;
        changed.validate()?;
        *self = changed;
        Ok(())
    }

    fn set_unchecked(&mut self, key: &str, value: &str) -> Result<(), SliceError> {
        let bad = |hint: &str| SliceError::BadSetting {
            key: key.to_string(),
            value: value.to_string(),
            hint: hint.to_string(),
        };
        let number = || {
            value
                .trim()
                .trim_end_matches('%')
                .parse::<f64>()
                .map_err(|_| bad("expected a number"))
        };
        match key {
            "layer_height" | "layer_height_mm" => self.layer_height_mm = Some(number()?),
            "infill" | "infill_percent" => self.infill_percent = Some(number()?),
            "supports" => {
                self.supports = Some(match value.trim().to_ascii_lowercase().as_str() {
                    "true" | "yes" | "on" | "1" => true,
                    "false" | "no" | "off" | "0" => false,
                    _ => return Err(bad("expected true or false")),
                })
            }
            "nozzle_temp" | "nozzle_temp_c" => self.nozzle_temp_c = Some(number()?),
            "bed_temp" | "bed_temp_c" => self.bed_temp_c = Some(number()?),
            "material" => self.material = Some(value.trim().to_ascii_lowercase()),
            _ => {
                return Err(bad(&format!(
                    "unknown setting; known settings: {}",
                    SETTING_KEYS.join(", ")
                )))
            }
        }
        Ok(())
    }

    /// Checks every given setting is within what an Ultimaker 2 with a 0.4 mm nozzle can do.
    pub fn validate(&self) -> Result<(), SliceError> {
        fn range(
            key: &str,
            v: Option<f64>,
            lo: f64,
            hi: f64,
            unit: &str,
        ) -> Result<(), SliceError> {
            match v {
                Some(x) if !(x.is_finite() && x >= lo && x <= hi) => Err(SliceError::BadSetting {
                    key: key.into(),
                    value: x.to_string(),
                    hint: format!("must be between {lo} and {hi} {unit}"),
                }),
                _ => Ok(()),
            }
        }
        range(
            "layer_height",
            self.layer_height_mm,
            0.05,
            0.32,
            "mm (0.4 mm nozzle)",
        )?;
        range("infill", self.infill_percent, 0.0, 100.0, "%")?;
        range("nozzle_temp", self.nozzle_temp_c, 150.0, 270.0, "°C")?;
        range("bed_temp", self.bed_temp_c, 0.0, 110.0, "°C")?;
        self.material_preset().map(|_| ())
    }

    /// The material preset named (PLA when none is).
    pub(crate) fn material_preset(&self) -> Result<&'static Material, SliceError> {
        let name = self.material.as_deref().unwrap_or("pla");
        MATERIALS
            .iter()
            .find(|m| m.name.eq_ignore_ascii_case(name))
            .ok_or_else(|| SliceError::BadSetting {
                key: "material".into(),
                value: name.into(),
                hint: format!(
                    "known materials: {}",
                    MATERIALS
                        .iter()
                        .map(|m| m.name)
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            })
    }

    /// The temperatures a job heats to: the explicit ones, else the material's.
    pub fn temperatures(&self) -> Result<(f64, f64), SliceError> {
        let m = self.material_preset()?;
        Ok((
            self.nozzle_temp_c.unwrap_or(m.nozzle_temp_c),
            self.bed_temp_c.unwrap_or(m.bed_temp_c),
        ))
    }
}
