//! Placing a mesh for printing: turning a Y-up model upright, scaling it to its printed
//! height, and putting it on the bed (lowest point at Z = 0, footprint centred on
//! X = Y = 0, where each slicer centres it on its own bed), with a check that it fits.

use super::Mesh;

/// Why a mesh cannot be placed on a bed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlaceError {
    #[error("the model has no volume to print (empty or flat mesh)")]
    Empty,
    #[error("at the asked height the model is {size_mm:.1?} mm (X, Y, Z), more than the {max_mm:?} mm that fit")]
    TooBig { size_mm: [f64; 3], max_mm: [f64; 3] },
}

/// Which of the model file's axes points up. STL files are Z-up by convention; many OBJ
/// files (the Stanford bunny, Spot) are Y-up and would otherwise print lying on their side.
#[derive(Clone, Copy, Debug, serde::Serialize, serde::Deserialize, PartialEq, Eq, Default)]
#[serde(rename_all = "lowercase")]
pub enum UpAxis {
    #[default]
    Z,
    Y,
}

impl std::str::FromStr for UpAxis {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "z" => Ok(UpAxis::Z),
            "y" => Ok(UpAxis::Y),
            _ => Err(format!("unknown up axis {s:?}; use z or y")),
        }
    }
}

/// A right-handed turn about X by +90°: the model's Y axis becomes Z (up), Z becomes -Y.
pub fn turn_y_up(mesh: &mut Mesh) {
    for v in &mut mesh.vertices {
        *v = [v[0], -v[2], v[1]];
    }
}

/// Uniformly scales `mesh` about the origin so its Z extent (Z is up, as slicers place
/// it) is `height_mm`. Returns the factor used; a flat mesh or a non-positive height
/// leaves the mesh unchanged and returns 1.
pub fn scale_to_height(mesh: &mut Mesh, height_mm: f64) -> f64 {
    let Some((lo, hi)) = mesh.bounds() else {
        return 1.0;
    };
    let extent = hi[2] - lo[2];
    if !(extent > 0.0 && height_mm.is_finite() && height_mm > 0.0) {
        return 1.0;
    }
    let s = height_mm / extent;
    for v in &mut mesh.vertices {
        for c in v.iter_mut() {
            *c *= s;
        }
    }
    s
}

/// Scales the mesh to `height_mm` tall, puts its lowest point at Z = 0 and centres its
/// footprint on X = Y = 0, and checks it fits `fits_mm` (X, Y, Z) (infinite: any size).
/// Returns the model's size (X, Y, Z) in mm.
pub fn place_on_bed(
    mesh: &mut Mesh,
    height_mm: f64,
    fits_mm: [f64; 3],
) -> Result<[f64; 3], PlaceError> {
    let (lo, hi) = mesh.bounds().ok_or(PlaceError::Empty)?;
    // Written so that a NaN extent counts as flat too.
    let height = hi[2] - lo[2];
    if mesh.faces.is_empty() || height.is_nan() || height <= 0.0 {
        return Err(PlaceError::Empty);
    }
    scale_to_height(mesh, height_mm);
    let (lo, hi) = mesh.bounds().ok_or(PlaceError::Empty)?;
    let shift = [-(lo[0] + hi[0]) / 2.0, -(lo[1] + hi[1]) / 2.0, -lo[2]];
    for v in &mut mesh.vertices {
        for k in 0..3 {
            v[k] += shift[k];
        }
    }
    let size = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
    check_fits(size, fits_mm)?;
    Ok(size)
}

/// Whether a placed model of `size_mm` (X, Y, Z) fits `fits_mm`: placement is the same
/// on every bed (centred, at the printed height), so one placed mesh is checked against
/// each machine's bed.
pub fn check_fits(size_mm: [f64; 3], fits_mm: [f64; 3]) -> Result<(), PlaceError> {
    if (0..3).any(|k| !(size_mm[k] <= fits_mm[k] + 1e-9)) {
        return Err(PlaceError::TooBig {
            size_mm,
            max_mm: fits_mm,
        });
    }
    Ok(())
}
