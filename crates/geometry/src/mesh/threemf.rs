//! 3MF: a zip of XML "model" parts. We read every `*.model` part, resolve the root
//! model's `<build>` items through `<components>` (also across parts, as PrusaSlicer and
//! Bambu Studio write them), apply the item and component transforms, convert the model
//! unit to millimetres, and return one mesh. Materials, colours and slicer metadata do
//! not affect the shape and are ignored.

use super::{Limits, MeshError, MeshFormat, RawMesh};
use quick_xml::events::{BytesStart, Event};
use std::collections::{HashMap, HashSet};
use std::io::{Cursor, Read};

/// Affine map in 3MF's row-vector convention: p' = p·A + t, stored as rows of A, then t.
type Transform = [[f64; 3]; 4];
const IDENTITY: Transform = [[1., 0., 0.], [0., 1., 0.], [0., 0., 1.], [0., 0., 0.]];

fn apply(t: &Transform, p: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|k| p[0] * t[0][k] + p[1] * t[1][k] + p[2] * t[2][k] + t[3][k])
}

/// `first`, then `then`.
fn compose(first: &Transform, then: &Transform) -> Transform {
    let mut out = [[0.0; 3]; 4];
    for (r, row) in first.iter().enumerate().take(3) {
        out[r] = std::array::from_fn(|k| {
            row[0] * then[0][k] + row[1] * then[1][k] + row[2] * then[2][k]
        });
    }
    out[3] = apply(then, first[3]);
    out
}

enum Object {
    Mesh {
        vertices: Vec<[f64; 3]>,
        triangles: Vec<[u32; 3]>,
    },
    Components(Vec<Component>),
}

struct Component {
    part: String,
    object_id: String,
    transform: Transform,
}

struct Part {
    unit_mm: f64,
    objects: HashMap<String, Object>,
    /// The objects' `name` attributes, by id.
    names: HashMap<String, String>,
    build: Vec<(String, Transform)>,
}

pub(super) fn parse(
    bytes: &[u8],
    source_name: &str,
    limits: &Limits,
) -> Result<RawMesh, MeshError> {
    let err = |location: &str, message: String| MeshError::Parse {
        source_name: source_name.to_string(),
        format: MeshFormat::ThreeMf,
        location: location.to_string(),
        message,
    };
    let mut archive = zip::ZipArchive::new(Cursor::new(bytes)).map_err(|e| {
        err(
            "zip container",
            format!("not a readable 3MF (zip) file: {e}"),
        )
    })?;
    let part_names: Vec<String> = archive
        .file_names()
        .filter(|n| n.to_ascii_lowercase().ends_with(".model"))
        .map(String::from)
        .collect();
    let root = part_names
        .iter()
        .find(|n| n.eq_ignore_ascii_case("3D/3dmodel.model"))
        .or_else(|| part_names.first())
        .cloned()
        .ok_or_else(|| {
            err(
                "zip container",
                "no 3D model part (3D/3dmodel.model) inside".into(),
            )
        })?;

    let mut parts: HashMap<String, Part> = HashMap::new();
    let mut budget_bytes = limits.max_xml_bytes;
    for name in &part_names {
        let mut file = archive
            .by_name(name)
            .map_err(|e| err(name, format!("cannot open part: {e}")))?;
        // A small zip can inflate to a huge part; keep decompression within the budget.
        let mut xml = Vec::new();
        (&mut file)
            .take(budget_bytes.saturating_add(1))
            .read_to_end(&mut xml)
            .map_err(|e| err(name, format!("cannot decompress part: {e}")))?;
        if xml.len() as u64 > budget_bytes {
            return Err(MeshError::TooLarge {
                source_name: source_name.to_string(),
                what: "bytes of uncompressed XML",
                count: limits.max_xml_bytes - budget_bytes + xml.len() as u64,
                limit: limits.max_xml_bytes,
            });
        }
        budget_bytes -= xml.len() as u64;
        let part = parse_part(&xml, name, source_name, limits)?;
        parts.insert(normalise_part_name(name), part);
    }

    let root_key = normalise_part_name(&root);
    let root_part = &parts[&root_key];
    let mut out = RawMesh {
        vertices: Vec::new(),
        faces: Vec::new(),
        objects: Vec::new(),
    };
    let unit = [
        [root_part.unit_mm, 0., 0.],
        [0., root_part.unit_mm, 0.],
        [0., 0., root_part.unit_mm],
        [0.; 3],
    ];
    let items: Vec<(String, Transform)> = if root_part.build.is_empty() {
        // No build section (the spec requires one, but some exporters leave it out):
        // take every object that is not a component of another, so that an assembly's
        // parts are not counted twice.
        let used: HashSet<&str> = root_part
            .objects
            .values()
            .filter_map(|o| match o {
                Object::Components(components) => Some(components),
                Object::Mesh { .. } => None,
            })
            .flatten()
            .filter(|c| c.part.is_empty() || normalise_part_name(&c.part) == root_key)
            .map(|c| c.object_id.as_str())
            .collect();
        let mut ids: Vec<&String> = root_part
            .objects
            .keys()
            .filter(|id| !used.contains(id.as_str()))
            .collect();
        ids.sort();
        ids.into_iter().map(|id| (id.clone(), IDENTITY)).collect()
    } else {
        root_part.build.clone()
    };
    let mut instances = 0;
    for (id, transform) in &items {
        let t = compose(transform, &unit);
        let at = Place {
            part: &root_key,
            id,
            transform: &t,
            depth: 0,
        };
        flatten(&parts, at, &mut instances, &mut out, source_name, limits)?;
        let name = root_part
            .names
            .get(id)
            .cloned()
            .unwrap_or_else(|| format!("object {id}"));
        out.objects.push((name, out.faces.len()));
    }
    Ok(out)
}

fn normalise_part_name(name: &str) -> String {
    name.trim_start_matches('/').to_ascii_lowercase()
}

/// Where [`flatten`] is in the component tree.
#[derive(Clone, Copy)]
struct Place<'a> {
    part: &'a str,
    id: &'a str,
    transform: &'a Transform,
    depth: usize,
}

/// Appends the object at `at`, with its components expanded, to `out`; `instances`
/// counts the objects visited (against `limits.max_instances`).
fn flatten(
    parts: &HashMap<String, Part>,
    at: Place<'_>,
    instances: &mut usize,
    out: &mut RawMesh,
    source_name: &str,
    limits: &Limits,
) -> Result<(), MeshError> {
    let Place {
        part,
        id,
        transform,
        depth,
    } = at;
    let err = |message: String| MeshError::Parse {
        source_name: source_name.to_string(),
        format: MeshFormat::ThreeMf,
        location: format!("{part}: object {id}"),
        message,
    };
    if depth > 32 {
        return Err(err("components nest more than 32 deep (a cycle?)".into()));
    }
    *instances += 1;
    if *instances > limits.max_instances {
        return Err(MeshError::TooLarge {
            source_name: source_name.to_string(),
            what: "object instances (components expanded)",
            count: *instances as u64,
            limit: limits.max_instances as u64,
        });
    }
    let object = parts
        .get(part)
        .and_then(|p| p.objects.get(id))
        .ok_or_else(|| {
            err("the build or a component refers to an object that does not exist".into())
        })?;
    match object {
        Object::Mesh {
            vertices,
            triangles,
        } => {
            if out.vertices.len() + vertices.len() > limits.max_vertices {
                return Err(MeshError::TooLarge {
                    source_name: source_name.to_string(),
                    what: "vertices",
                    count: (out.vertices.len() + vertices.len()) as u64,
                    limit: limits.max_vertices as u64,
                });
            }
            if out.faces.len() + triangles.len() > limits.max_faces {
                return Err(MeshError::TooLarge {
                    source_name: source_name.to_string(),
                    what: "triangles",
                    count: (out.faces.len() + triangles.len()) as u64,
                    limit: limits.max_faces as u64,
                });
            }
            let base = out.vertices.len() as u32;
            out.vertices
                .extend(vertices.iter().map(|&v| apply(transform, v)));
            out.faces
                .extend(triangles.iter().map(|t| t.map(|i| i + base)));
        }
        Object::Components(components) => {
            for c in components {
                let t = compose(&c.transform, transform);
                let target = if c.part.is_empty() {
                    part.to_string()
                } else {
                    normalise_part_name(&c.part)
                };
                let inner = Place {
                    part: &target,
                    id: &c.object_id,
                    transform: &t,
                    depth: depth + 1,
                };
                flatten(parts, inner, instances, out, source_name, limits)?;
            }
        }
    }
    Ok(())
}

fn parse_part(
    xml: &[u8],
    part_name: &str,
    source_name: &str,
    limits: &Limits,
) -> Result<Part, MeshError> {
    let err = |message: String| MeshError::Parse {
        source_name: source_name.to_string(),
        format: MeshFormat::ThreeMf,
        location: part_name.to_string(),
        message,
    };
    let mut reader = quick_xml::Reader::from_reader(xml);
    let mut buf = Vec::new();
    let mut part = Part {
        unit_mm: 1.0,
        objects: HashMap::new(),
        names: HashMap::new(),
        build: Vec::new(),
    };
    // The object being read: its id, and its mesh or components so far.
    type ObjectSoFar = (String, Vec<[f64; 3]>, Vec<[u32; 3]>, Vec<Component>);
    let mut current: Option<ObjectSoFar> = None;
    let mut total_vertices = 0usize;
    let mut total_triangles = 0usize;
    loop {
        let event = reader.read_event_into(&mut buf).map_err(|e| {
            err(format!(
                "invalid XML at byte {}: {e}",
                reader.error_position()
            ))
        })?;
        match &event {
            Event::Start(e) | Event::Empty(e) => {
                let attrs = attributes(e).map_err(&err)?;
                let get = |k: &str| attrs.get(k).map(String::as_str);
                match e.local_name().as_ref() {
                    b"model" => {
                        part.unit_mm = match get("unit").unwrap_or("millimeter") {
                            "micron" => 0.001,
                            "millimeter" => 1.0,
                            "centimeter" => 10.0,
                            "inch" => 25.4,
                            "foot" => 304.8,
                            "meter" => 1000.0,
                            other => return Err(err(format!("unknown model unit {other:?}"))),
                        };
                    }
                    b"object" => {
                        let id = get("id").ok_or_else(|| err("an <object> has no id".into()))?;
                        if let Some(name) = get("name").map(str::trim).filter(|n| !n.is_empty()) {
                            part.names.insert(id.to_string(), name.to_string());
                        }
                        current = Some((id.to_string(), Vec::new(), Vec::new(), Vec::new()));
                    }
                    b"vertex" => {
                        let (_, vertices, _, _) = current
                            .as_mut()
                            .ok_or_else(|| err("<vertex> outside an <object>".into()))?;
                        let mut v = [0.0f64; 3];
                        for (k, name) in ["x", "y", "z"].iter().enumerate() {
                            let text = get(name)
                                .ok_or_else(|| err(format!("a <vertex> has no {name}")))?;
                            v[k] = text.trim().parse().map_err(|_| {
                                err(format!("vertex coordinate {text:?} is not a number"))
                            })?;
                        }
                        if !v.iter().all(|c| c.is_finite()) {
                            return Err(MeshError::NonFinite {
                                source_name: source_name.to_string(),
                                location: format!("{part_name}: vertex {}", vertices.len()),
                            });
                        }
                        total_vertices += 1;
                        if total_vertices > limits.max_vertices {
                            return Err(MeshError::TooLarge {
                                source_name: source_name.to_string(),
                                what: "vertices",
                                count: total_vertices as u64,
                                limit: limits.max_vertices as u64,
                            });
                        }
                        vertices.push(v);
                    }
                    b"triangle" => {
                        let (_, _, triangles, _) = current
                            .as_mut()
                            .ok_or_else(|| err("<triangle> outside an <object>".into()))?;
                        let mut t = [0u32; 3];
                        for (k, name) in ["v1", "v2", "v3"].iter().enumerate() {
                            let text = get(name)
                                .ok_or_else(|| err(format!("a <triangle> has no {name}")))?;
                            t[k] = text.trim().parse().map_err(|_| {
                                err(format!("triangle index {text:?} is not a vertex index"))
                            })?;
                        }
                        total_triangles += 1;
                        if total_triangles > limits.max_faces {
                            return Err(MeshError::TooLarge {
                                source_name: source_name.to_string(),
                                what: "triangles",
                                count: total_triangles as u64,
                                limit: limits.max_faces as u64,
                            });
                        }
                        triangles.push(t);
                    }
                    b"component" => {
                        let (_, _, _, components) = current
                            .as_mut()
                            .ok_or_else(|| err("<component> outside an <object>".into()))?;
                        let object_id = get("objectid")
                            .ok_or_else(|| err("a <component> has no objectid".into()))?
                            .to_string();
                        components.push(Component {
                            part: get("path").unwrap_or("").to_string(),
                            object_id,
                            transform: parse_transform(get("transform")).map_err(&err)?,
                        });
                    }
                    b"item" => {
                        let object_id = get("objectid")
                            .ok_or_else(|| err("a build <item> has no objectid".into()))?
                            .to_string();
                        let t = parse_transform(get("transform")).map_err(&err)?;
                        part.build.push((object_id, t));
                    }
                    _ => {}
                }
            }
            Event::End(e) if e.local_name().as_ref() == b"object" => {
                if let Some((id, vertices, triangles, components)) = current.take() {
                    let object = if components.is_empty() {
                        if let Some(bad) = triangles
                            .iter()
                            .flatten()
                            .find(|&&i| i as usize >= vertices.len())
                        {
                            return Err(err(format!(
                                "object {id}: a triangle refers to vertex {bad}, but the object has {} vertices",
                                vertices.len()
                            )));
                        }
                        Object::Mesh {
                            vertices,
                            triangles,
                        }
                    } else {
                        Object::Components(components)
                    };
                    part.objects.insert(id, object);
                }
            }
            Event::Eof => break,
            _ => {}
        }
        buf.clear();
    }
    Ok(part)
}

fn attributes(e: &BytesStart) -> Result<HashMap<String, String>, String> {
    let mut out = HashMap::new();
    for a in e.attributes() {
        let a = a.map_err(|e| format!("invalid XML attribute: {e}"))?;
        let key = String::from_utf8_lossy(a.key.local_name().as_ref()).into_owned();
        let value = a
            .unescape_value()
            .map_err(|e| format!("invalid XML attribute value: {e}"))?
            .into_owned();
        out.insert(key, value);
    }
    Ok(out)
}

fn parse_transform(text: Option<&str>) -> Result<Transform, String> {
    let Some(text) = text else {
        return Ok(IDENTITY);
    };
    let numbers: Vec<f64> = text
        .split_ascii_whitespace()
        .map(|t| t.parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("transform {text:?} is not 12 numbers"))?;
    if numbers.len() != 12 || !numbers.iter().all(|x| x.is_finite()) {
        return Err(format!("transform {text:?} is not 12 finite numbers"));
    }
    Ok(std::array::from_fn(|r| {
        std::array::from_fn(|k| numbers[r * 3 + k])
    }))
}
