//! What is visible of a picture, band by band and place by place, and how much of it
//! differs between two pictures of one framing.
//!
//! [`perceive`]: luminance → Peli's local band-limited contrast (E. Peli, "Contrast in
//! complex images", JOSA A 7(10), 1990: per octave band, the band-pass picture divided by
//! the low-pass one below it, the local mean luminance; here in the pyramid form Peli
//! describes, each level the band between it and the next) → in multiples of the
//! detection threshold, by [`eye::barten_csf`] at the band's frequency, the local mean
//! luminance and the print's angular size.
//!
//! [`compare`]: in each region of each band, the difference between the two pictures'
//! visible contrast (its amplitude there, whatever its phase) in multiples of the
//! threshold as the weaker of the two raises it (mutual masking, Daly 1993: a pattern
//! masks a difference in its band only as far as both pictures hold it), summed to the
//! power [`eye::BETA`] (probability summation). Where the reference's contrast is the
//! stronger the difference is a feature lost; where the candidate's is, one added.

use super::eye::{self, CsfTable};
use super::pyramid::{expand, reduce, reduce_max, Plane};
use rayon::prelude::*;

/// What is visible of one picture: per level of its pyramid, each place's band-limited
/// contrast in multiples of its threshold (signed), and which places the print covers.
pub(crate) struct Perceived {
    pub(crate) levels: Vec<Plane>,
    pub(crate) region: Vec<Plane>,
    /// Each level's frequency, cycles per degree.
    pub(crate) cpd: Vec<f64>,
}

/// Where level `level` of the pyramid responds, in cycles per pixel of the picture (its
/// finest level), and its response there. Measured on the
/// pyramid itself with gratings of every frequency and several phases (the test
/// `the_levels_respond_where_they_are_said_to` measures them again): the centroid of the
/// level's response over log frequency, and its peak response. Level 0, the difference
/// between the picture and its low-pass, is a high-pass up to the Nyquist frequency;
/// every level below it is the one above at half the frequency, except that level 1 is
/// still a little wider.
fn level_response(level: usize) -> (f64, f64) {
    match level {
        0 => (0.213, 1.0),
        1 => (0.0885, 0.648),
        j => (0.168 / f64::from(1u32 << j.min(30)), 0.59),
    }
}

/// The frequency of pyramid level `level` of a picture at `ppd` pixels per degree,
/// cycles per degree.
pub(crate) fn level_cpd(ppd: f64, level: usize) -> f64 {
    ppd * level_response(level).0
}

/// The local mean below which Peli's ratio is not taken, cd/m²: a room's darkest shadow.
const MIN_MEAN_LUMINANCE: f32 = 0.01;

/// Perceives `luminance` (cd/m²) seen at `ppd` pixels per degree: `levels` octave bands,
/// the finest first; `coverage` says where the print is, and `field_deg` is its angular
/// size (Barten's X0).
pub(crate) fn perceive(
    luminance: &Plane,
    coverage: &Plane,
    ppd: f64,
    field_deg: f64,
    levels: usize,
) -> Perceived {
    let mut out = Perceived {
        levels: Vec::with_capacity(levels),
        region: Vec::with_capacity(levels),
        cpd: Vec::with_capacity(levels),
    };
    let mut g = luminance.clone();
    let mut region = coverage.clone();
    for j in 0..levels {
        let next = reduce(&g);
        let mean = expand(&next, g.width, g.height);
        let cpd = level_cpd(ppd, j);
        // Peli's bands take a grating at their centre whole; the pyramid's levels overlap,
        // and take a grating at a level's centre at `gain` of its contrast.
        let gain = level_response(j).1 as f32;
        let csf = CsfTable::new(cpd, field_deg);
        let mut n = Plane::filled(g.width, g.height, 0.0);
        n.data
            .par_chunks_mut(g.width.max(1) * 16)
            .zip(g.data.par_chunks(g.width.max(1) * 16))
            .zip(mean.data.par_chunks(g.width.max(1) * 16))
            .for_each(|((n, g), mean)| {
                for i in 0..n.len() {
                    let m = mean[i].max(MIN_MEAN_LUMINANCE);
                    n[i] = (g[i] - mean[i]) / (m * gain) * csf.at(m);
                }
            });
        out.levels.push(n);
        let coarser = reduce_max(&region);
        out.region.push(region);
        region = coarser;
        out.cpd.push(cpd);
        g = next;
    }
    out
}

/// The sums of one band of one comparison: Σ d^β where the reference's feature is the
/// stronger (lost) and where the candidate's is (added), and the number of regions the
/// print covers in either picture (the band's area, in regions).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct BandSums {
    pub(crate) lost: f64,
    pub(crate) added: f64,
    pub(crate) area: f64,
}

/// The visible contrast of band `n` region by region, whatever its phase: the local
/// amplitude of the band's response, √(n² + (R₁n)² + (R₂n)²) with R the Riesz transform
/// (the monogenic signal's amplitude, Felsberg & Sommer 2001), R approximated on a
/// pyramid level by central differences as in Wadhwa et al.'s Riesz pyramids (ICCP
/// 2014, whose bands are centred at a quarter cycle per pixel; here scaled to be exact at
/// the level's own centre), its square averaged by two steps of the pyramid's low-pass: one value per
/// region of 4 × 4 pixels of the band, one to two of its wavelengths across. For a
/// grating, its amplitude. Two prints of different sizes are registered only as a whole
/// (their layers fall at different heights of the model, and an enhancement that moves
/// the model's extremes rescales it by a fraction of a percent), so a feature moved by
/// less than its own size must count as the same feature: its sign, pixel by pixel,
/// would count it as lost and added.
fn energy(n: &Plane, level: usize) -> Plane {
    // The central difference's response to a grating of ω radians per pixel is sin ω:
    // divided by it at the level's centre, the approximation is exact there.
    let omega =
        2.0 * std::f64::consts::PI * level_response(level).0 * f64::from(1u32 << level.min(30));
    let scale = (0.5 / omega.sin()) as f32;
    let (w, h) = (n.width, n.height);
    let at = |x: isize, y: isize| {
        n.data[y.clamp(0, h as isize - 1) as usize * w + x.clamp(0, w as isize - 1) as usize]
    };
    let mut squared = Plane::filled(w, h, 0.0);
    squared
        .data
        .par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            let y = y as isize;
            for (x, out) in row.iter_mut().enumerate() {
                let x = x as isize;
                let r1 = scale * (at(x + 1, y) - at(x - 1, y));
                let r2 = scale * (at(x, y + 1) - at(x, y - 1));
                let v = at(x, y);
                *out = v * v + r1 * r1 + r2 * r2;
            }
        });
    let mut e = reduce(&reduce(&squared));
    e.data.iter_mut().for_each(|v| *v = v.max(0.0).sqrt());
    e
}

/// Compares `candidate` with `reference`, both of one framing, the candidate's level j
/// being the reference's level j + `offset` (its picture 2^offset times coarser), region
/// by region ([`energy`]). A band of the reference the candidate has no level for (finer
/// than its pixels) is compared with nothing: all it shows is lost. Per reference level,
/// the sums.
pub(crate) fn compare(
    reference: &Perceived,
    candidate: &Perceived,
    offset: usize,
) -> Vec<BandSums> {
    (0..reference.levels.len())
        .map(|j| {
            let r = energy(&reference.levels[j], j);
            let r_region = reduce_max(&reduce_max(&reference.region[j]));
            let c = j.checked_sub(offset).and_then(|k| {
                Some((
                    energy(candidate.levels.get(k)?, k),
                    reduce_max(&reduce_max(candidate.region.get(k)?)),
                ))
            });
            if let Some((c, _)) = &c {
                debug_assert_eq!((r.width, r.height), (c.width, c.height));
            }
            (0..r.height)
                .into_par_iter()
                .map(|y| {
                    let mut sums = BandSums::default();
                    for x in 0..r.width {
                        let i = y * r.width + x;
                        let er = f64::from(r.data[i]);
                        let (ec, inside_c) = match &c {
                            Some((c, region)) => (f64::from(c.data[i]), region.data[i] > 0.0),
                            None => (0.0, false),
                        };
                        if r_region.data[i] > 0.0 || inside_c {
                            sums.area += 1.0;
                        }
                        if er == ec {
                            continue;
                        }
                        let d = (er - ec).abs() / eye::daly_elevation(er.min(ec));
                        let p = d.powf(eye::BETA);
                        if er > ec {
                            sums.lost += p;
                        } else {
                            sums.added += p;
                        }
                    }
                    sums
                })
                .reduce(BandSums::default, |a, b| BandSums {
                    lost: a.lost + b.lost,
                    added: a.added + b.added,
                    area: a.area + b.area,
                })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn picture(w: usize, h: usize, f: impl Fn(f64, f64) -> f64) -> Plane {
        Plane {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| f((i % w) as f64 + 0.5, (i / w) as f64 + 0.5) as f32)
                .collect(),
        }
    }

    /// Gratings of every frequency and several phases through the pyramid: each level
    /// responds around the frequency [`level_response`] says, as strongly as it says.
    #[test]
    fn the_levels_respond_where_they_are_said_to() {
        // Six levels: a seventh's response reaches below the lowest frequency tried.
        let (w, h, levels) = (4096, 4, 6);
        let freqs: Vec<f64> = (0..160)
            .map(|i| 0.0008 * (0.5f64 / 0.0008).powf(f64::from(i) / 159.0))
            .collect();
        let mut response = vec![vec![0.0f64; freqs.len()]; levels];
        for (k, &f) in freqs.iter().enumerate() {
            for phase in [0.0, 0.5, 1.1, 1.9, 2.6] {
                let mut g = picture(w, h, |x, _| {
                    1.0 + 0.1 * (2.0 * std::f64::consts::PI * f * x + phase).sin()
                });
                for level in response.iter_mut() {
                    let next = reduce(&g);
                    let mean = expand(&next, g.width, g.height);
                    let (a, b) = (g.width / 4, 3 * g.width / 4);
                    let rms = ((a..b)
                        .map(|x| f64::from(g.at(x, 0) - mean.at(x, 0)).powi(2))
                        .sum::<f64>()
                        / (b - a) as f64)
                        .sqrt();
                    // As a share of the grating's amplitude, over the phases.
                    level[k] += rms * std::f64::consts::SQRT_2 / 0.1 / 5.0;
                    g = next;
                }
            }
        }
        for (j, r) in response.iter().enumerate() {
            let peak = r.iter().copied().fold(0.0, f64::max);
            let centroid = (r.iter().zip(&freqs).map(|(r, f)| r * f.ln()).sum::<f64>()
                / r.iter().sum::<f64>())
            .exp();
            let (said_f, said_peak) = level_response(j);
            assert!(
                (centroid / said_f - 1.0).abs() < 0.05,
                "level {j}: {centroid} c/px"
            );
            assert!(
                (peak / said_peak - 1.0).abs() < 0.05,
                "level {j}: peak {peak}"
            );
        }
    }

    /// A grating at a level's centre shows in that level at its contrast times the
    /// sensitivity there (in threshold units), whatever its phase, region by region.
    #[test]
    fn a_grating_shows_in_its_band_as_contrast_times_sensitivity() {
        let ppd = 64.0;
        let (w, h) = (256, 256);
        let f = level_response(2).0;
        let grating = picture(w, h, |x, _| {
            100.0 * (1.0 + 0.05 * (2.0 * std::f64::consts::PI * f * x).sin())
        });
        let p = perceive(&grating, &Plane::filled(w, h, 1.0), ppd, 10.0, 5);
        let e = energy(&p.levels[2], 2);
        // The middle of the picture, away from its edges.
        let middle: Vec<f32> = (e.height / 4..3 * e.height / 4)
            .flat_map(|y| (e.width / 4..3 * e.width / 4).map(move |x| (x, y)))
            .map(|(x, y)| e.at(x, y))
            .collect();
        let s = 0.05 * eye::barten_csf(ppd * f, 100.0, 10.0) as f32;
        let (lo, hi) = middle
            .iter()
            .fold((f32::MAX, 0.0f32), |(l, h), &v| (l.min(v), h.max(v)));
        assert!(lo > 0.85 * s && hi < 1.15 * s, "{lo}..{hi} against {s}");
    }

    /// A picture compared with itself differs nowhere; with a copy whose grating is
    /// stronger, the difference is added, with a weaker one, lost; and the reference's
    /// levels finer than the candidate's pixels are lost whatever the candidate is.
    #[test]
    fn lost_and_added_features() {
        let ppd = 64.0;
        let make = |c: f64| {
            let g = picture(128, 128, |x, y| {
                100.0 * (1.0 + c * (0.4 * x).sin() * (0.3 * y).cos())
            });
            perceive(&g, &Plane::filled(128, 128, 1.0), ppd, 5.0, 4)
        };
        let (base, weak, strong) = (make(0.2), make(0.05), make(0.5));
        let same = compare(&base, &base, 0);
        assert!(same.iter().all(|b| b.lost == 0.0 && b.added == 0.0));
        assert_eq!(same[0].area, 32.0 * 32.0);
        let total = |v: &[BandSums]| {
            v.iter()
                .fold((0.0, 0.0), |a, b| (a.0 + b.lost, a.1 + b.added))
        };
        let (lost, added) = total(&compare(&base, &weak, 0));
        assert!(lost > 0.0 && added < 1e-3 * lost, "{lost} {added}");
        let (lost, added) = total(&compare(&base, &strong, 0));
        assert!(added > 0.0 && lost < 1e-3 * added, "{lost} {added}");
        // The candidate one octave coarser: its level 0 is the reference's level 1.
        let coarse = {
            let g = picture(64, 64, |x, y| {
                100.0 * (1.0 + 0.2 * (0.8 * x).sin() * (0.6 * y).cos())
            });
            perceive(&g, &Plane::filled(64, 64, 1.0), ppd / 2.0, 5.0, 3)
        };
        let sums = compare(&base, &coarse, 1);
        assert_eq!(sums.len(), 4);
        assert_eq!(sums[0].added, 0.0);
        assert!(sums[0].lost > 0.0);
    }

    /// The comparison is of the amplitude of a band region by region, not of its phase:
    /// a pattern of many frequencies and directions moved by a pixel (a quarter to a half
    /// of the finest band's wavelength, a sixteenth of the coarsest's) differs far less
    /// than the same pattern a fifth stronger. (The pattern fades out towards the
    /// picture's edges, as a print does on its cloth.)
    #[test]
    fn a_pattern_moved_a_little_is_the_same_pattern() {
        let ppd = 64.0;
        let waves: Vec<(f64, f64, f64)> = (0..12)
            .map(|k| {
                let omega = 0.3 * (2.5f64 / 0.3).powf(f64::from(k) / 11.0);
                (omega, 1.7 * f64::from(k), 0.4 + 0.3 * f64::from(k).sin())
            })
            .collect();
        let make = |shift: f64, c: f64| {
            let g = picture(256, 256, |x, y| {
                let r2 = (x - 128.0).powi(2) + (y - 128.0).powi(2);
                let window = (-r2 / (2.0 * 50.0f64.powi(2))).exp();
                let sum: f64 = waves
                    .iter()
                    .map(|&(w, phase, dir)| {
                        (w * ((x + shift) * dir.cos() + y * dir.sin()) + phase).sin()
                    })
                    .sum();
                100.0 * (1.0 + c * window * sum / waves.len() as f64)
            });
            perceive(&g, &Plane::filled(256, 256, 1.0), ppd, 5.0, 5)
        };
        let base = make(0.0, 0.5);
        let total = |v: Vec<BandSums>| v.iter().map(|b| b.lost + b.added).sum::<f64>();
        let moved = total(compare(&base, &make(1.0, 0.5), 0));
        let stronger = total(compare(&base, &make(0.0, 0.6), 0));
        assert!(moved < 0.1 * stronger, "moved {moved}, stronger {stronger}");
    }
}
