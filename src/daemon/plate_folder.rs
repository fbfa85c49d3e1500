//! A folder of models dropped into a hot folder as one job: a plate of several models.
//!
//! The folder holds the models and [`PLATE_SIDECAR`], a sidecar that names them
//! (`models = ["gear.stl", "nut.obj"]`) beside any key a model's sidecar takes. The pick-up
//! packs the folder into one 3MF whose build holds each model as an object named after its
//! file, writes the other keys as that 3MF's sidecar, and admits the 3MF: both stores and
//! the preparation then see what they see for any 3MF of several objects (a plate of its
//! models, each a part), and nothing else in the farm knows folders.
//!
//! The steps keep a kill at any point from losing a model or admitting it twice. All work
//! happens in the hot folder's hidden [`STAGING_DIR`] (on the hot folder's file system,
//! out of the watcher's sight): the 3MF and its sidecar are written there first, then the
//! folder is renamed in beside them, then the 3MF is admitted (the store moves it away:
//! that is the commit), then the staged folder is removed. [`recover`], at the pick-up's
//! start, finishes what a kill interrupted: a staged folder whose 3MF is still staged goes
//! back to the hot folder, one whose 3MF is gone was admitted and is removed.
//!
//! The folder is taken only whole: every file in it is a model named in `models` or the
//! sidecar itself (hidden files aside), so removing it after the pack loses nothing the
//! job does not hold. Everything here blocks: run it on a blocking thread.

use crate::daemon::hotfolder::{file_kind, same_name, FileKind};
use crate::mesh::{Limits, Mesh, MeshError};
use std::path::{Path, PathBuf};

/// The sidecar of a plate folder: the models it names and the job's other keys.
pub(crate) const PLATE_SIDECAR: &str = "plate.toml";

/// The folder in each hot folder where plate folders are packed (hidden: the watcher
/// never takes a name starting with a dot).
pub(crate) const STAGING_DIR: &str = ".crispen-plates";

/// What a staged plate folder's name ends with, beside its 3MF.
const STAGED_SUFFIX: &str = ".d";

/// Why a folder cannot be taken as a plate.
#[derive(Debug, thiserror::Error)]
pub(crate) enum PlateError {
    /// Perhaps still being copied in: waited for, then set aside.
    #[error("the folder has no {PLATE_SIDECAR} naming its models (a folder in a hot folder is one plate: put its models and a {PLATE_SIDECAR} with `models = [\"a.stl\", ...]` in it)")]
    NoSidecar,
    /// Perhaps still being copied in: waited for, then set aside.
    #[error("{PLATE_SIDECAR} names {0}, which is not in the folder")]
    Missing(String),
    #[error("{0}")]
    Sidecar(String),
    #[error("{PLATE_SIDECAR}: key `models`: {0}")]
    Models(String),
    #[error("{name} is in the folder but is not a model named in {PLATE_SIDECAR}'s `models` (a plate folder holds its models and {PLATE_SIDECAR} only, since it is removed once packed: take it out, or name it)")]
    Unnamed { name: String },
    #[error("{0}")]
    Mesh(#[from] MeshError),
    #[error("the models together have {what} {count}, more than one plate may ({limit})")]
    TooLarge {
        what: &'static str,
        count: usize,
        limit: usize,
    },
    #[error("cannot {what} {}: {source}", path.display())]
    Io {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl PlateError {
    /// Whether the folder may still be arriving (a copy over a share settles file by
    /// file): it is looked at again for a while before it is set aside.
    pub(crate) fn may_be_arriving(&self) -> bool {
        matches!(self, PlateError::NoSidecar | PlateError::Missing(_))
    }

    /// Whether the folder itself is at fault (it is set aside) rather than the machine
    /// (a full disk: it stays and is tried again).
    pub(crate) fn is_the_folders(&self) -> bool {
        !matches!(self, PlateError::Io { .. })
    }
}

fn io(what: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> PlateError {
    let path = path.to_path_buf();
    move |source| PlateError::Io { what, path, source }
}

/// A plate folder read: its models' meshes in the order named, each with its part's name,
/// and the job's sidecar without `models`.
struct Plate {
    models: Vec<(String, Mesh)>,
    sidecar: String,
}

/// A plate folder packed in its hot folder's [`STAGING_DIR`], ready to be admitted.
#[derive(Debug)]
pub(crate) struct Staged {
    /// The 3MF to admit (its sidecar beside it).
    pub model: PathBuf,
    /// The folder as it was dropped, renamed in beside it.
    pub folder: PathBuf,
}

/// Packs the plate folder `dir` of the hot folder `hot` (see the module's steps). On an
/// error nothing has moved: `dir` is where it was.
pub(crate) fn stage(dir: &Path, hot: &Path) -> Result<Staged, PlateError> {
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy())
        .unwrap_or_default();
    let plate = read(dir, &Limits::default())?;
    let staging = hot.join(STAGING_DIR);
    std::fs::create_dir_all(&staging).map_err(io("create", &staging))?;
    let model = staging.join(format!("{name}.3mf"));
    let folder = staging.join(format!("{name}{STAGED_SUFFIX}"));
    if std::fs::symlink_metadata(&folder).is_ok() {
        return Err(io("stage", &folder)(std::io::Error::new(
            std::io::ErrorKind::AlreadyExists,
            "a plate of this name is being packed already",
        )));
    }
    let staged = Staged { model, folder };
    let written = (|| {
        let objects: Vec<(&str, &Mesh)> =
            plate.models.iter().map(|(n, m)| (n.as_str(), m)).collect();
        crispen_fsutil::write_atomic_with(&staged.model, |file| {
            crate::mesh::write_3mf(std::io::BufWriter::new(file), &objects)?
                .into_inner()
                .map_err(|e| e.into_error())
                .map(drop)
        })
        .map_err(|e| io("write", &staged.model)(e.into()))?;
        let sidecar = sidecar_of(&staged.model);
        crispen_fsutil::write_atomic(&sidecar, plate.sidecar.as_bytes())
            .map_err(|e| io("write", &sidecar)(e.into()))?;
        std::fs::rename(dir, &staged.folder).map_err(io("move", dir))
    })();
    if let Err(e) = written {
        remove_packed(&staged.model);
        return Err(e);
    }
    Ok(staged)
}

impl Staged {
    /// The 3MF was admitted: the folder it was packed from goes.
    pub(crate) fn admitted(self) -> std::io::Result<()> {
        remove_packed(&self.model);
        std::fs::remove_dir_all(&self.folder)
    }

    /// The 3MF could not be admitted: the folder goes back to `dir` in its hot folder.
    pub(crate) fn undo(self, dir: &Path) -> std::io::Result<()> {
        remove_packed(&self.model);
        std::fs::rename(&self.folder, dir)
    }
}

/// The sidecar the store looks for beside `model` (`x.3mf.toml`).
fn sidecar_of(model: &Path) -> PathBuf {
    let mut name = model.as_os_str().to_owned();
    name.push(".toml");
    PathBuf::from(name)
}

/// Removes a staged 3MF and its sidecar where they are still there.
fn remove_packed(model: &Path) {
    for path in [model.to_path_buf(), sidecar_of(model)] {
        let _ = std::fs::remove_file(path);
    }
}

/// Finishes what a kill left in `hot`'s [`STAGING_DIR`] (see the module's steps): a staged
/// folder whose 3MF is still there goes back to the hot folder (it was never admitted),
/// one whose 3MF is gone is removed (it was). Returns the folders put back.
pub(crate) fn recover(hot: &Path) -> Vec<PathBuf> {
    let staging = hot.join(STAGING_DIR);
    let Ok(entries) = std::fs::read_dir(&staging) else {
        return Vec::new();
    };
    let mut back = Vec::new();
    for entry in entries.flatten() {
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(stem) = name.strip_suffix(STAGED_SUFFIX) else {
            continue;
        };
        let staged = Staged {
            model: staging.join(format!("{stem}.3mf")),
            folder: path,
        };
        let put_back = staged.model.exists();
        let folder = staged.folder.clone();
        let to = hot.join(stem);
        let done = match put_back {
            true if std::fs::symlink_metadata(&to).is_ok() => {
                tracing::error!(folder = %folder.display(), "a plate folder interrupted while packed cannot go back: its name is taken in the hot folder; move it back by hand");
                continue;
            }
            true => staged.undo(&to).map(|()| back.push(to.clone())),
            false => staged.admitted(),
        };
        match done {
            Ok(()) if put_back => {
                tracing::warn!(folder = %to.display(), "a plate folder interrupted while packed is back in its hot folder")
            }
            Ok(()) => {
                tracing::info!(folder = %folder.display(), "a plate folder admitted before an interruption is removed")
            }
            Err(e) => {
                tracing::error!(folder = %folder.display(), error = %e, "cannot finish a plate folder interrupted while packed")
            }
        }
    }
    // A pack interrupted before its folder moved leaves its 3MF alone: the folder is
    // still in the hot folder and is packed again.
    if let Ok(entries) = std::fs::read_dir(&staging) {
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            let stem = name
                .strip_suffix(".3mf.toml")
                .or_else(|| name.strip_suffix(".3mf"));
            if let Some(stem) = stem {
                if !staging.join(format!("{stem}{STAGED_SUFFIX}")).exists() {
                    let _ = std::fs::remove_file(entry.path());
                }
            }
        }
    }
    back
}

/// Reads a plate folder: its sidecar, the files it holds, each model's mesh.
fn read(dir: &Path, limits: &Limits) -> Result<Plate, PlateError> {
    let sidecar_path = dir.join(PLATE_SIDECAR);
    let text = match read_bounded(&sidecar_path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(PlateError::NoSidecar),
        Err(e) => return Err(io("read", &sidecar_path)(e)),
    };
    let (names, sidecar) = parse(&text, &sidecar_path)?;
    let listed = std::fs::read_dir(dir).map_err(io("list", dir))?;
    let mut files = Vec::new();
    for entry in listed {
        let entry = entry.map_err(io("list", dir))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') || name == PLATE_SIDECAR {
            continue;
        }
        if !names.iter().any(|n| same_name(n, &name)) {
            return Err(PlateError::Unnamed {
                name: crate::names::escaped(&name),
            });
        }
        let kind = entry.file_type().map_err(io("look at", &entry.path()))?;
        if !kind.is_file() {
            return Err(PlateError::Models(format!(
                "{} is not a regular file (a link or a folder is not taken)",
                crate::names::escaped(&name)
            )));
        }
        files.push((name, entry.path()));
    }
    let (mut vertices, mut faces) = (0, 0);
    let mut models = Vec::new();
    for wanted in &names {
        let Some((name, path)) = files.iter().find(|(n, _)| same_name(n, wanted)) else {
            return Err(PlateError::Missing(crate::names::escaped(wanted)));
        };
        let file = std::fs::File::open(path).map_err(io("read", path))?;
        let mesh = crate::mesh::read_with_limits(file, &path.display().to_string(), limits)?.mesh;
        vertices += mesh.vertices.len();
        faces += mesh.faces.len();
        for (what, count, limit) in [
            ("vertices", vertices, limits.max_vertices),
            ("faces", faces, limits.max_faces),
        ] {
            if count > limit {
                return Err(PlateError::TooLarge { what, count, limit });
            }
        }
        // The part's name: the file's, without its extension.
        let part = name.rsplit_once('.').map_or(&name[..], |(stem, _)| stem);
        models.push((part.to_string(), mesh));
    }
    Ok(Plate { models, sidecar })
}

/// Reads a sidecar whole, refusing one larger than any sidecar is.
fn read_bounded(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let limit = crate::daemon::job::MAX_SIDECAR_BYTES;
    let mut text = String::new();
    std::fs::File::open(path)?
        .take(limit + 1)
        .read_to_string(&mut text)?;
    if text.len() as u64 > limit {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("larger than {limit} bytes; a sidecar holds a few keys"),
        ));
    }
    Ok(text)
}

/// The models a plate's sidecar names, and the sidecar the 3MF gets (the other keys,
/// checked here as a model's sidecar is, so an error names `plate.toml`).
fn parse(text: &str, path: &Path) -> Result<(Vec<String>, String), PlateError> {
    let mut table: toml::Table = toml::from_str(text).map_err(|e| {
        PlateError::Sidecar(format!(
            "sidecar {}: {}",
            path.display(),
            e.message().trim()
        ))
    })?;
    let models =
        match table.remove("models") {
            None => return Err(PlateError::Models(
                "missing: name the folder's models, e.g. `models = [\"gear.stl\", \"nut.obj\"]`"
                    .into(),
            )),
            Some(toml::Value::Array(models)) => models,
            Some(other) => {
                return Err(PlateError::Models(format!(
                    "must be a list of file names, got a {}",
                    other.type_str()
                )))
            }
        };
    let most = crate::slice::plate::MAX_PER_PLATE as usize;
    if models.is_empty() || models.len() > most {
        return Err(PlateError::Models(format!(
            "names {} models; a plate holds 1 to {most}",
            models.len()
        )));
    }
    let mut names: Vec<String> = Vec::new();
    for model in models {
        let toml::Value::String(name) = model else {
            return Err(PlateError::Models(format!(
                "must be a list of file names, got a {}",
                model.type_str()
            )));
        };
        let shown = crate::names::escaped(&name);
        if let Some(problem) = crate::names::problem(&name) {
            return Err(PlateError::Models(format!("{shown}: its name {problem}")));
        }
        if name.contains('/') || name.starts_with('.') || name == PLATE_SIDECAR {
            return Err(PlateError::Models(format!(
                "{shown}: a model is named by its file name in the folder"
            )));
        }
        if file_kind(&name) != Some(FileKind::Model) {
            return Err(PlateError::Models(format!(
                "{shown}: a plate's models are STL, OBJ or 3MF files"
            )));
        }
        if names.iter().any(|n| same_name(n, &name)) {
            return Err(PlateError::Models(format!("{shown} is named twice")));
        }
        let stem = |n: &str| n.rsplit_once('.').map_or(n, |(s, _)| s).to_string();
        if names.iter().any(|n| same_name(&stem(n), &stem(&name))) {
            return Err(PlateError::Models(format!(
                "{shown}: another model has its name (each part is named after its file, without the extension)"
            )));
        }
        names.push(name);
    }
    let sidecar = toml::to_string(&table)
        .map_err(|e| PlateError::Sidecar(format!("sidecar {}: {e}", path.display())))?;
    crate::daemon::job::parse_sidecar(sidecar.as_bytes(), path).map_err(PlateError::Sidecar)?;
    Ok((names, sidecar))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tetra(at: f64) -> Mesh {
        Mesh {
            vertices: vec![
                [at, 0.0, 0.0],
                [at + 10.0, 0.0, 0.0],
                [at, 10.0, 0.0],
                [at, 0.0, 10.0],
            ],
            faces: vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]],
        }
    }

    /// A hot folder with a plate folder `set` of `gear.stl` and `nut.obj` and `sidecar`.
    fn plate(sidecar: &str) -> (tempfile::TempDir, PathBuf, PathBuf) {
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path().join("hot");
        let dir = hot.join("set");
        std::fs::create_dir_all(&dir).unwrap();
        crate::mesh::save(&dir.join("gear.stl"), &tetra(0.0)).unwrap();
        crate::mesh::save(&dir.join("nut.obj"), &tetra(20.0)).unwrap();
        std::fs::write(dir.join(PLATE_SIDECAR), sidecar).unwrap();
        (tmp, hot, dir)
    }

    fn error(sidecar: &str) -> String {
        let (_tmp, hot, dir) = plate(sidecar);
        let e = stage(&dir, &hot).unwrap_err();
        assert!(dir.join("gear.stl").exists(), "nothing moved on {e}");
        e.to_string()
    }

    #[test]
    fn a_plate_folder_is_packed_as_one_3mf_of_its_models_in_the_order_named() {
        let (_tmp, hot, dir) =
            plate("models = [\"nut.obj\", \"gear.stl\"]\nper_plate = 2\nhold = true\n");
        std::fs::write(dir.join(".DS_Store"), "x").unwrap();
        let staged = stage(&dir, &hot).unwrap();
        assert!(!dir.exists(), "the folder is out of the watcher's sight");
        assert_eq!(staged.model, hot.join(STAGING_DIR).join("set.3mf"));
        let loaded = crate::mesh::load(&staged.model).unwrap();
        let names: Vec<&str> = loaded.objects.iter().map(|o| o.name.as_str()).collect();
        assert_eq!(names, ["nut", "gear"]);
        let nut = loaded.mesh.sub(loaded.objects[0].faces.clone());
        assert_eq!(nut.vertices, tetra(20.0).vertices);
        let sidecar = crate::daemon::job::read_sidecar(&sidecar_of(&staged.model))
            .unwrap()
            .unwrap();
        assert_eq!((sidecar.per_plate, sidecar.hold), (Some(2), Some(true)));
        staged.admitted().unwrap();
        let left: Vec<_> = std::fs::read_dir(hot.join(STAGING_DIR)).unwrap().collect();
        assert!(left.is_empty(), "{left:?}");
    }

    #[test]
    fn a_plate_folder_refused_says_what_and_moves_nothing() {
        for (sidecar, expected) in [
            ("hold = true\n", "key `models`: missing"),
            (
                "models = \"gear.stl\"\n",
                "must be a list of file names, got a string",
            ),
            ("models = []\n", "names 0 models"),
            (
                "models = [\"gear.stl\"]\n",
                "nut.obj is in the folder but is not a model named",
            ),
            (
                "models = [\"gear.stl\", \"nut.obj\", \"bolt.stl\"]\n",
                "names bolt.stl, which is not in the folder",
            ),
            (
                "models = [\"gear.stl\", \"../nut.obj\"]\n",
                "is named by its file name",
            ),
            (
                "models = [\"gear.stl\", \"nut.obj\", \"gear.stl\"]\n",
                "gear.stl is named twice",
            ),
            (
                "models = [\"gear.stl\", \"gear.obj\"]\n",
                "another model has its name",
            ),
            (
                "models = [\"gear.stl\", \"nut.gcode\"]\n",
                "STL, OBJ or 3MF",
            ),
            (
                "models = [\"gear.stl\", \"nut.obj\"]\ncolor = \"red\"\n",
                "plate.toml: unknown field `color`",
            ),
            (
                "models = [\"gear.stl\", \"nut.obj\"]\nheight_mm = -3\n",
                "key `height_mm`",
            ),
            ("models = [\"gear.stl\", \"nut.obj\"\n", "plate.toml"),
        ] {
            let e = error(sidecar);
            assert!(e.contains(expected), "{sidecar:?}: {e}");
        }
        let (_tmp, hot, dir) = plate("");
        std::fs::remove_file(dir.join(PLATE_SIDECAR)).unwrap();
        let e = stage(&dir, &hot).unwrap_err();
        assert!(e.may_be_arriving() && e.is_the_folders(), "{e}");
        let (_tmp, hot, dir) = plate("models = [\"gear.stl\", \"nut.obj\"]\n");
        std::fs::write(dir.join("nut.obj"), "v 0 0 0\n").unwrap();
        let e = stage(&dir, &hot).unwrap_err();
        assert!(
            matches!(e, PlateError::Mesh(_)) && e.to_string().contains("nut.obj"),
            "{e}"
        );
    }

    #[test]
    fn a_pack_interrupted_by_a_kill_is_finished_at_the_next_start() {
        // Killed after the folder moved in, before the admission: it goes back.
        let (_tmp, hot, dir) = plate("models = [\"gear.stl\", \"nut.obj\"]\n");
        stage(&dir, &hot).unwrap();
        assert_eq!(recover(&hot), vec![dir.clone()]);
        assert!(dir.join("gear.stl").exists());
        let left: Vec<_> = std::fs::read_dir(hot.join(STAGING_DIR)).unwrap().collect();
        assert!(left.is_empty(), "{left:?}");
        // Killed after the admission took the 3MF, before the folder was removed: it goes.
        let staged = stage(&dir, &hot).unwrap();
        std::fs::remove_file(&staged.model).unwrap();
        assert!(recover(&hot).is_empty());
        assert!(!staged.folder.exists() && !dir.exists());
        // Killed while packing, before the folder moved: the stale pack goes, the folder
        // stays to be packed again.
        let (_tmp, hot, dir) = plate("models = [\"gear.stl\", \"nut.obj\"]\n");
        let staged = stage(&dir, &hot).unwrap();
        std::fs::rename(&staged.folder, &dir).unwrap();
        assert!(recover(&hot).is_empty());
        assert!(!staged.model.exists() && dir.join("nut.obj").exists());
    }
}
