//! The pictures, checked by what they show: known shapes give their known silhouettes, the
//! lighting shows the surface, the heat map varies where the displacement does, the G-code
//! thumbnails read back as PNGs in PrusaSlicer's format, `crispen enhance --preview`
//! writes all three pictures, and the print drawn from real G-code shows the enhancement
//! where the walls moved (`crispen slice --preview`).

use crate::common;

use crispen::daemon::prepare::steps::{prepare_one, SliceRequest, Target};
use crispen::enhance::{self, EnhanceOptions, Strength};
use crispen::machine::Machine;
use crispen::mesh::place::UpAxis;
use crispen::mesh::{self, Mesh};
use crispen::preview::{self, thumbnail, Camera, Image, Lighting, Paint, MODEL_COLOR};
use std::process::Command;

/// A sphere of radius 1 around the origin: an icosahedron subdivided and pushed out.
fn sphere() -> Mesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let vertices = vec![
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ];
    let faces = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    let mut mesh = common::subdivide(&Mesh { vertices, faces }, 12);
    for v in &mut mesh.vertices {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        *v = v.map(|c| c / n);
    }
    mesh
}

/// A box from (0, 0, 0) to `size`, as 12 triangles.
fn cuboid(size: [f64; 3]) -> Mesh {
    let vertices = (0..8)
        .map(|i| std::array::from_fn(|k| if i >> k & 1 == 1 { size[k] } else { 0.0 }))
        .collect();
    let quads = [
        [0, 1, 3, 2],
        [4, 6, 7, 5],
        [0, 4, 5, 1],
        [2, 3, 7, 6],
        [0, 2, 6, 4],
        [1, 5, 7, 3],
    ];
    let faces = quads
        .iter()
        .flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]])
        .collect();
    Mesh { vertices, faces }
}

fn opaque(image: &Image) -> impl Iterator<Item = (u32, u32, [u8; 4])> + '_ {
    (0..image.height)
        .flat_map(move |y| (0..image.width).map(move |x| (x, y, image.pixel(x, y))))
        .filter(|p| p.2[3] >= 128)
}

#[test]
fn a_sphere_from_any_side_is_a_disk_of_its_radius() {
    let sphere = sphere();
    let bounds = sphere.bounds().unwrap();
    for eye in [[0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [-0.3, 1.0, 0.2]] {
        let camera = Camera::looking_at(bounds, eye, [0.0, 0.0, 1.0], 200, 160);
        let image = preview::render(&sphere, &camera, Paint::Uniform(MODEL_COLOR));
        let radius_px = camera.scale;
        let expected = std::f64::consts::PI * radius_px * radius_px;
        let area = opaque(&image).count() as f64;
        assert!(
            (area - expected).abs() < 0.02 * expected,
            "from {eye:?}: {area} pixels covered, a disk of radius {radius_px:.1} has {expected:.0}"
        );
        // Every covered pixel lies within the disk (plus one pixel of edge).
        let (cx, cy) = (100.0, 80.0);
        for (x, y, _) in opaque(&image) {
            let r = ((x as f64 + 0.5 - cx).powi(2) + (y as f64 + 0.5 - cy).powi(2)).sqrt();
            assert!(r < radius_px + 1.0, "pixel ({x}, {y}) outside the disk");
        }
        assert_eq!(image.pixel(0, 0)[3], 0, "the background is transparent");
        assert_eq!(image.pixel(100, 80)[3], 255);
    }
}

#[test]
fn a_box_from_the_front_is_its_rectangle() {
    let box_mesh = cuboid([40.0, 10.0, 20.0]);
    let camera = Camera::looking_at(
        box_mesh.bounds().unwrap(),
        [0.0, -1.0, 0.0],
        [0.0, 0.0, 1.0],
        300,
        300,
    );
    let image = preview::render(&box_mesh, &camera, Paint::Uniform(MODEL_COLOR));
    let (mut x0, mut x1, mut y0, mut y1) = (u32::MAX, 0, u32::MAX, 0);
    for (x, y, _) in opaque(&image) {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    let (width, height) = (f64::from(x1 - x0 + 1), f64::from(y1 - y0 + 1));
    assert!((width - 40.0 * camera.scale).abs() <= 2.0, "width {width}");
    assert!(
        (height - 20.0 * camera.scale).abs() <= 2.0,
        "height {height}"
    );
    assert!(
        width > 1.9 * height,
        "the picture's x is the model's x, its y the model's z"
    );
    // Seen face on, the front face is evenly lit: one colour inside the rectangle.
    let inner: Vec<[u8; 4]> = opaque(&image)
        .filter(|&(x, y, _)| x > x0 + 2 && x + 2 < x1 && y > y0 + 2 && y + 2 < y1)
        .map(|p| p.2)
        .collect();
    assert!(inner.windows(2).all(|w| w[0] == w[1]));
}

#[test]
fn lighting_shows_the_shape_from_above_left() {
    let sphere = sphere();
    let camera = Camera::looking_at(
        sphere.bounds().unwrap(),
        [0.0, -1.0, 0.0],
        [0.0, 0.0, 1.0],
        200,
        200,
    );
    let image = preview::render(&sphere, &camera, Paint::Uniform(MODEL_COLOR));
    let brightness = |x: u32, y: u32| {
        let p = image.pixel(x, y);
        u32::from(p[0]) + u32::from(p[1]) + u32::from(p[2])
    };
    let r = camera.scale as u32;
    // Upper left of the disk faces the light; lower right faces away.
    let lit = brightness(100 - r / 2, 100 - r / 2);
    let shadow = brightness(100 + r / 2, 100 + r / 2);
    assert!(lit > shadow + 150, "lit {lit}, shadow {shadow}");
}

/// How much the colour (not the brightness) varies over the covered pixels: the standard
/// deviation of the green share g / (r + g + b).
fn chroma_spread(image: &Image) -> f64 {
    let shares: Vec<f64> = opaque(image)
        .filter_map(|(_, _, p)| {
            let sum = f64::from(p[0]) + f64::from(p[1]) + f64::from(p[2]);
            (sum > 60.0).then(|| f64::from(p[1]) / sum)
        })
        .collect();
    let mean = shares.iter().sum::<f64>() / shares.len() as f64;
    (shares.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / shares.len() as f64).sqrt()
}

#[test]
fn the_heat_map_varies_where_the_displacement_does() {
    let spot = mesh::load(&common::model("spot.obj")).unwrap().mesh;
    let (enhanced, _) =
        enhance::enhance(&spot, &EnhanceOptions::with_lambda2(20.0), &mut |_| {}).unwrap();
    let pictures = preview::pictures(&spot, &enhanced, UpAxis::Y, 256).unwrap();
    assert!(pictures.max_displacement > 0.0);

    // Per vertex: the most displaced vertex is at the top of the ramp, the least at the bottom.
    let (colors, max) = preview::displacement_colors(&spot, &enhanced);
    assert_eq!(max, pictures.max_displacement);
    let moved: Vec<f64> = spot
        .vertices
        .iter()
        .zip(&enhanced.vertices)
        .map(|(a, b)| (0..3).map(|k| (b[k] - a[k]).powi(2)).sum::<f64>().sqrt())
        .collect();
    let argmax = (0..moved.len())
        .max_by(|&i, &j| moved[i].total_cmp(&moved[j]))
        .unwrap();
    let argmin = (0..moved.len())
        .min_by(|&i, &j| moved[i].total_cmp(&moved[j]))
        .unwrap();
    assert_eq!(colors[argmax], preview::heat_color(1.0));
    assert!(colors[argmin][2] > colors[argmin][1], "least moved is blue");

    // In the picture: an unmoved mesh's heat map is one colour under varying light; the
    // enhanced one's colour varies far more.
    let still = preview::pictures(&spot, &spot, UpAxis::Y, 256).unwrap();
    let (flat, varied) = (
        chroma_spread(&still.displacement),
        chroma_spread(&pictures.displacement),
    );
    assert!(
        varied > 0.02 && varied > 4.0 * flat,
        "colour spread {varied} (enhanced) vs {flat} (unmoved)"
    );

    // Before and after: one camera, so nearly the same silhouette, but not the same picture.
    let coverage = |i: &Image| opaque(i).count() as f64;
    let (b, a) = (coverage(&pictures.before), coverage(&pictures.after));
    assert!((a - b).abs() < 0.03 * b, "coverage {b} before, {a} after");
    assert_ne!(pictures.before, pictures.after);
}

fn decode_png(bytes: &[u8]) -> Image {
    let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    let mut reader = decoder.read_info().unwrap();
    let mut rgba = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut rgba).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgba);
    Image {
        width: info.width,
        height: info.height,
        rgba,
    }
}

#[test]
fn gcode_thumbnails_read_back_in_prusaslicer_format() {
    let dir = tempfile::tempdir().unwrap();
    let gcode = dir.path().join("part.gcode");
    let original = "; generated by PrusaSlicer 2.5.0\nG28\nG1 X10 Y10 ; move\nM84\n";
    std::fs::write(&gcode, original).unwrap();
    let spot = mesh::load(&common::model("spot.obj")).unwrap().mesh;
    thumbnail::insert_into_file(&gcode, &thumbnail::blocks(&spot, UpAxis::Y)).unwrap();
    let text = std::fs::read_to_string(&gcode).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines[0], "; generated by PrusaSlicer 2.5.0");

    // Parse the blocks back as another tool would.
    let mut found = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        if let Some(rest) = lines[i].strip_prefix("; thumbnail begin ") {
            let (size, len) = rest.split_once(' ').unwrap();
            let len: usize = len.parse().unwrap();
            let mut data = String::new();
            i += 1;
            while lines[i] != "; thumbnail end" {
                let chunk = lines[i].strip_prefix("; ").unwrap();
                assert!(chunk.len() <= 78, "line {i} too long");
                data.push_str(chunk);
                i += 1;
            }
            assert_eq!(data.len(), len, "the length in the header");
            use base64::Engine;
            let png = base64::engine::general_purpose::STANDARD
                .decode(&data)
                .unwrap();
            let image = decode_png(&png);
            assert_eq!(format!("{}x{}", image.width, image.height), size);
            assert!(
                opaque(&image).count() as f64 > 0.1 * f64::from(image.width * image.height),
                "{size}: the part is in the picture"
            );
            found.push(size.to_string());
        }
        i += 1;
    }
    assert_eq!(found, ["300x300", "32x32"]);

    // Without the comments, the G-code is exactly what it was.
    let commands: Vec<&str> = lines
        .iter()
        .copied()
        .filter(|l| !l.starts_with(';'))
        .collect();
    assert_eq!(commands, ["G28", "G1 X10 Y10 ; move", "M84"]);
}

#[test]
fn enhance_command_writes_the_three_pictures() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("spot.stl");
    let pictures = dir.path().join("pictures");
    let result = Command::new(env!("CARGO_BIN_EXE_crispen"))
        .args(["enhance", common::model("spot.obj").to_str().unwrap(), "-o"])
        .arg(&out)
        .args(["--strength", "15", "--up", "y", "--preview"])
        .arg(&pictures)
        .output()
        .unwrap();
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let read = |name: &str| decode_png(&std::fs::read(pictures.join(name)).unwrap());
    let (before, after, heat) = (
        read(preview::BEFORE_PNG),
        read(preview::AFTER_PNG),
        read(preview::DISPLACEMENT_PNG),
    );
    for image in [&before, &after, &heat] {
        assert_eq!((image.width, image.height), (800, 800));
        assert!(opaque(image).count() > 800 * 800 / 10);
    }
    assert_ne!(before, after);
    assert!(chroma_spread(&heat) > 2.0 * chroma_spread(&after));
}

/// Slices the bunny at 20 mm for a 0.4 mm nozzle with PrusaSlicer, at `strength`, into
/// `out`.
fn slice_bunny(strength: Strength, out: &std::path::Path) {
    let mut req = SliceRequest::new(common::model("bunny.obj"), 20.0);
    req.up = UpAxis::Y;
    req.strength = strength;
    let target = Target {
        machine: Machine::builtin("ultimaker2plus").unwrap(),
        output: out.to_path_buf(),
        keep_mesh: None,
    };
    prepare_one(&req, target, &mut |_| {}).expect("sliced");
}

/// The print drawn from the G-code shows the enhancement where the nozzle's path moved:
/// seen level (so that each picture row is one height of the print), the rows of the
/// layers whose outer wall moved most differ between the plain and the enhanced print
/// more than the rows of the layers that moved least; a stronger enhancement changes more.
#[test]
fn the_enhanced_print_differs_from_the_plain_one_where_the_walls_moved() {
    use crispen::preview::print::{read_print_file, render_print};
    use crispen::slice::walls;
    let dir = tempfile::tempdir().unwrap();
    let (plain_path, enhanced_path) = (dir.path().join("plain.gcode"), dir.path().join("e.gcode"));
    slice_bunny(Strength::Off, &plain_path);
    slice_bunny(Strength::Auto, &enhanced_path);
    let read_walls = |p: &std::path::Path| {
        walls::outer_walls(std::io::BufReader::new(std::fs::File::open(p).unwrap())).unwrap()
    };
    let comparison = walls::compare(&read_walls(&plain_path), &read_walls(&enhanced_path), 0.4);
    let (plain, enhanced) = (
        read_print_file(&plain_path, 0.4).unwrap(),
        read_print_file(&enhanced_path, 0.4).unwrap(),
    );
    assert_eq!(plain.stride, 1, "a 20 mm bunny is drawn whole");
    assert!(plain.segment_count() > 10_000, "{}", plain.segment_count());

    // Level, from the front-right: a row is a height.
    let (lo, hi) = plain.bounds().unwrap();
    let size = 400;
    let camera = Camera::looking_at((lo, hi), [0.5, -0.866, 0.0], [0.0, 0.0, 1.0], size, size);
    let light = Lighting::grazing(&camera, [0.0, 0.0, 1.0], 20.0);
    let (p, e) = (
        render_print(&plain, &camera, &light),
        render_print(&enhanced, &camera, &light),
    );
    assert_ne!(p, e);
    let row_of = |z: f64| {
        let y = 0.5 * f64::from(size) - (z - camera.center[2]) * camera.scale;
        y.clamp(0.0, f64::from(size) - 1.0) as u32
    };
    // Per layer: the share of its rows' drawn pixels that differ.
    let differs = |y: u32| {
        let (mut drawn, mut changed) = (0, 0);
        for x in 0..size {
            let (a, b) = (p.pixel(x, y), e.pixel(x, y));
            if a[3] > 0 || b[3] > 0 {
                drawn += 1;
                changed += u32::from((0..4).any(|k| a[k].abs_diff(b[k]) > 12));
            }
        }
        (drawn, changed)
    };
    let mut layers: Vec<(f64, f64)> = comparison
        .per_layer
        .iter()
        // The first layers are the bed's and the top ones the ears' tips: too few rows.
        .filter(|l| l.z_mm > 1.0 && l.z_mm < hi[2] - 1.0)
        .map(|l| {
            let (top, bottom) = (row_of(l.z_mm), row_of(l.z_mm - 0.2));
            let (drawn, changed) = (top..=bottom)
                .map(differs)
                .fold((0, 0), |s, d| (s.0 + d.0, s.1 + d.1));
            (l.mean_mm, f64::from(changed) / f64::from(drawn.max(1)))
        })
        .collect();
    assert!(layers.len() > 60, "{} layers", layers.len());
    layers.sort_by(|a, b| a.0.total_cmp(&b.0));
    let quarter = layers.len() / 4;
    let mean = |s: &[(f64, f64)]| s.iter().map(|l| l.1).sum::<f64>() / s.len() as f64;
    let (least, most) = (
        mean(&layers[..quarter]),
        mean(&layers[layers.len() - quarter..]),
    );
    assert!(
        most > 1.3 * least && most > 0.05,
        "rows of the most moved layers differ {most:.3}, of the least moved {least:.3}"
    );

    // A stronger enhancement (λ2 = 40 against the default 20 at this height) shows more.
    let stronger_path = dir.path().join("e40.gcode");
    slice_bunny(Strength::Lambda2(40.0), &stronger_path);
    let stronger = render_print(
        &read_print_file(&stronger_path, 0.4).unwrap(),
        &camera,
        &light,
    );
    let changed = |other: &Image| {
        (0..size)
            .flat_map(|y| (0..size).map(move |x| (x, y)))
            .filter(|&(x, y)| {
                let (a, b) = (p.pixel(x, y), other.pixel(x, y));
                (0..4).any(|k| a[k].abs_diff(b[k]) > 12)
            })
            .count()
    };
    let (at_20, at_40) = (changed(&e), changed(&stronger));
    assert!(
        at_40 > at_20,
        "λ2 40 changes {at_40} pixels, the default {at_20}"
    );
}

/// `crispen slice --preview DIR` writes DIR/preview.png: the model, the plain print and
/// the enhanced one in a row of panels, the prints at their size below; a PNG of bounded
/// size in which the enhanced panel differs from the plain one.
#[test]
fn slice_command_writes_the_preview_of_the_print() {
    use crispen::preview::print::{PANEL_PX, PREVIEW_PNG};
    let dir = tempfile::tempdir().unwrap();
    let preview_dir = dir.path().join("preview");
    let result = Command::new(env!("CARGO_BIN_EXE_crispen"))
        .args(["slice", common::model("bunny.obj").to_str().unwrap(), "-o"])
        .arg(dir.path().join("bunny.gcode"))
        .args(["--height", "20", "--up", "y", "--machine", "ultimaker2plus"])
        .arg("--preview")
        .arg(&preview_dir)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&result.stdout);
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let path = preview_dir.join(PREVIEW_PNG);
    assert!(
        stdout.contains(&format!("wrote {}", path.display())),
        "{stdout}"
    );
    let bytes = std::fs::read(&path).unwrap();
    assert!(bytes.len() < 4 << 20, "{} bytes", bytes.len());
    let image = decode_png(&bytes);
    let gap = 8;
    assert_eq!(image.width, 3 * PANEL_PX + 2 * gap);
    assert!(image.height > PANEL_PX + gap + 40 && image.height <= 2 * PANEL_PX + gap);
    let panel = |k: u32| {
        let x0 = k * (PANEL_PX + gap);
        (0..PANEL_PX)
            .flat_map(|y| (x0..x0 + PANEL_PX).map(move |x| (x, y)))
            .map(|(x, y)| image.pixel(x, y))
            .collect::<Vec<_>>()
    };
    let (mesh, plain, enhanced) = (panel(0), panel(1), panel(2));
    let drawn = |p: &[[u8; 4]]| p.iter().filter(|c| c[3] > 0).count();
    for p in [&mesh, &plain, &enhanced] {
        assert!(
            drawn(p) > (PANEL_PX * PANEL_PX / 8) as usize,
            "a panel is filled"
        );
    }
    let differ = plain
        .iter()
        .zip(&enhanced)
        .filter(|(a, b)| (0..4).any(|k| a[k].abs_diff(b[k]) > 12))
        .count();
    assert!(
        differ > 1000 && differ < drawn(&plain),
        "{differ} pixels differ"
    );
    // The strip at the printed size: a 20 mm bunny at 4 px/mm is about 80 px tall.
    let strip: usize = (PANEL_PX + gap..image.height)
        .filter(|&y| (0..image.width).any(|x| image.pixel(x, y)[3] > 0))
        .count();
    assert!(
        (60..=140).contains(&strip),
        "{strip} rows at the printed size"
    );
}
