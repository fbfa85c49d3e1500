//! The pictures kept with each job, from its printer's camera: a snapshot when the print
//! starts, after its first layer, at its end, and at a failure with the last frames before
//! it; and a timelapse, a frame at each layer change (or every N seconds), encoded to MP4
//! once the print is over. The recorder follows the printer's published state, as the
//! notifier does, and never touches the print: a camera that is slow, lying or down costs
//! a missing picture, logged, and nothing else. What a job has is in its `camera.json`,
//! written by the recorder alone, with the layers its timelapse has no frame of and why
//! (a camera that dies mid-print leaves a short timelapse that says so).

use super::hub::{Cameras, NoFrame, Picture};
use super::timelapse;
use crate::daemon::config::camera::Timelapse;
use crate::daemon::farm::{Farm, PrinterLive};
use crate::daemon::job::JobState;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

/// What a job's camera folder holds (`camera.json`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JobCamera {
    pub printer: String,
    /// The snapshots in the order taken: `start`, `first-layer`, `end`, `failure`, and
    /// `before-failure-N` (oldest first).
    pub snapshots: Vec<Snapshot>,
    pub timelapse: Option<TimelapseInfo>,
    /// Why the timelapse is missing, when it is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub timelapse_error: Option<String>,
    /// The print's layers (from its layer comments; 1 when it has none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layers: Option<u32>,
    /// The layers the timelapse has no frame of, in runs of one cause, oldest first.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub missing: Vec<MissingFrames>,
    /// The parts of the plate the print dropped, where the timelapse shows it.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub dropped: Vec<DroppedPart>,
}

/// A part of the plate cancelled during the print: from which frame of the timelapse it is
/// no longer printed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DroppedPart {
    pub part: String,
    /// The layer it was dropped at (from 1), where the G-code tells.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layer: Option<usize>,
    /// The frames taken before it was dropped: the next is the first without it.
    pub frame: u32,
    /// Where that frame is in the encoded timelapse, seconds.
    pub video_s: f64,
}

/// Layers `first..=last` (from 1) of a print have no timelapse frame, for one cause.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MissingFrames {
    pub first: u32,
    pub last: u32,
    /// Why, as it was when the first of them was missed.
    pub why: NoFrame,
    /// Unix seconds when the first of them was missed.
    pub at: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Snapshot {
    pub name: String,
    /// The file in the job's camera folder.
    pub file: String,
    /// Unix seconds when the camera took it.
    pub at: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TimelapseInfo {
    pub file: String,
    pub frames: u32,
    pub bytes: u64,
}

/// The manifest's name in a job's camera folder.
pub const MANIFEST: &str = "camera.json";
/// The frames waiting for the encoder, in a job's camera folder.
const FRAMES_DIR: &str = "frames";
/// How often the recorder looks, besides each change of its printer.
const TICK: Duration = Duration::from_secs(1);
/// Frames kept in memory to show what came before a failure.
const BEFORE_FAILURE: usize = 3;

/// A print being recorded.
struct Recording {
    job: String,
    dir: PathBuf,
    manifest: JobCamera,
    /// Command index at which each layer after the first starts (from the G-code).
    layer_starts: Vec<usize>,
    next_layer: usize,
    frames: u32,
    /// The frames an earlier attempt at the print left, which come first.
    earlier_frames: u32,
    last_frame: Option<Instant>,
    first_layer_taken: bool,
    /// The latest distinct pictures, for a failure.
    recent: VecDeque<Picture>,
}

/// Records the jobs of `printer` until `stop`; timelapses are encoded in `encodes`.
pub async fn record(
    farm: Arc<Farm>,
    cameras: Arc<Cameras>,
    printer: String,
    encodes: TaskTracker,
    stop: CancellationToken,
) {
    let mut printers = farm.watch_printers();
    let mut recording: Option<Recording> = None;
    loop {
        let Some(handle) = farm.printer(&printer) else {
            tokio::select! {
                r = printers.changed() => if r.is_err() { return },
                _ = stop.cancelled() => return,
            }
            continue;
        };
        let mut live = handle.live;
        loop {
            let now = live.borrow_and_update().clone();
            step(&farm, &cameras, &printer, &encodes, &mut recording, &now).await;
            tokio::select! {
                r = live.changed() => if r.is_err() { break },
                _ = tokio::time::sleep(TICK) => {}
                _ = stop.cancelled() => break,
            }
        }
        if stop.is_cancelled() {
            if let Some(rec) = recording.take() {
                finish(&farm, &cameras, &printer, &encodes, rec).await;
            }
            return;
        }
    }
}

async fn step(
    farm: &Farm,
    cameras: &Arc<Cameras>,
    printer: &str,
    encodes: &TaskTracker,
    recording: &mut Option<Recording>,
    live: &PrinterLive,
) {
    let current = live
        .job
        .as_deref()
        .filter(|_| live.state.has_print_under_way());
    if let Some(rec) = recording.take_if(|r| current != Some(r.job.as_str())) {
        finish(farm, cameras, printer, encodes, rec).await;
    }
    let Some(job) = current else { return };
    if recording.is_none() {
        *recording = Some(start(farm, cameras, printer, job).await);
    }
    let Some(rec) = recording.as_mut() else {
        return;
    };
    let acked = live.progress.as_ref().map_or(0, |p| p.lines_acked);
    follow(cameras, printer, rec, acked).await;
    mark_dropped(farm, cameras.settings.timelapse, rec).await;
}

/// Marks in the manifest, once each, the parts the store says this print dropped: with a
/// frame a layer, before the frame of the layer it was dropped at (whenever the recorder
/// sees it); else at the frame the timelapse has come to.
async fn mark_dropped(farm: &Farm, timelapse: Timelapse, rec: &mut Recording) {
    let dropped: Vec<(String, Option<usize>)> = {
        let store = farm.store();
        let Some(job) = store.get(&rec.job) else {
            return;
        };
        job.parts_cancelled_in(job.print_number())
            .filter(|c| !rec.manifest.dropped.iter().any(|d| d.part == c.part))
            .filter_map(|c| Some((c.part.clone(), c.dropped.as_ref()?.layer)))
            .collect()
    };
    if dropped.is_empty() {
        return;
    }
    for (part, layer) in dropped {
        let frame = match (timelapse, layer) {
            (Timelapse::Layers, Some(layer)) => {
                // The layers before it, less those the camera gave no frame of.
                let before = layer.saturating_sub(1) as u32;
                let missed: u32 = rec
                    .manifest
                    .missing
                    .iter()
                    .map(|m| m.last.min(before).saturating_sub(m.first.saturating_sub(1)))
                    .sum();
                rec.earlier_frames + before.saturating_sub(missed)
            }
            _ => rec.frames,
        };
        tracing::info!(printer = %rec.manifest.printer, job = %rec.job, part, frame, "camera: the timelapse marks a part dropped");
        rec.manifest.dropped.push(DroppedPart {
            part,
            layer,
            frame,
            video_s: timelapse::seconds_at(frame),
        });
    }
    write_manifest(&rec.dir, &rec.manifest).await;
}

/// The printer's picture now, if its camera has a fresh one (decoding off the runtime);
/// why not otherwise.
async fn picture(cameras: &Arc<Cameras>, printer: &str) -> Result<Picture, NoFrame> {
    let (cams, name) = (Arc::clone(cameras), printer.to_string());
    match tokio::task::spawn_blocking(move || cams.fresh_picture(&name)).await {
        Ok(Some(got)) => got,
        // No camera (the recorder runs for printers with one), or the decoder panicked.
        Ok(None) | Err(_) => Err(NoFrame::Picture),
    }
}

async fn start(farm: &Farm, cameras: &Arc<Cameras>, printer: &str, job: &str) -> Recording {
    let dir = cameras.root().join(job);
    // The first layer's snapshot needs them whatever the timelapse does.
    let layer_starts = layer_starts_of(farm, printer, job).await;
    let layers = layer_starts.len() as u32 + 1;
    tracing::info!(printer, job, layers, folder = %dir.display(), "camera: recording the print");
    let mut rec = Recording {
        job: job.to_string(),
        dir,
        manifest: JobCamera {
            printer: printer.to_string(),
            ..JobCamera::default()
        },
        layer_starts,
        next_layer: 0,
        frames: 0,
        earlier_frames: 0,
        last_frame: None,
        first_layer_taken: false,
        recent: VecDeque::new(),
    };
    // A restart mid-print finds the folder of the job's earlier attempt: kept, added to.
    if let Ok(text) = tokio::fs::read(rec.dir.join(MANIFEST)).await {
        if let Ok(old) = serde_json::from_slice::<JobCamera>(&text) {
            rec.manifest = old;
        }
    }
    // Frames an earlier attempt left unencoded come first in the timelapse.
    rec.frames = frames_kept(&rec.dir).await;
    rec.earlier_frames = rec.frames;
    rec.manifest.layers = Some(layers);
    if let Ok(p) = picture(cameras, printer).await {
        snapshot(&mut rec, "start", &p).await;
    }
    rec
}

/// Takes the frames the print's progress calls for: timelapse frames, the first layer.
async fn follow(cameras: &Arc<Cameras>, printer: &str, rec: &mut Recording, acked: usize) {
    let mut crossed = 0;
    while rec
        .layer_starts
        .get(rec.next_layer)
        .is_some_and(|&s| acked > s)
    {
        rec.next_layer += 1;
        crossed += 1;
    }
    let timed = match cameras.settings.timelapse {
        Timelapse::Every(every) => rec.last_frame.is_none_or(|t| t.elapsed() >= every),
        _ => false,
    };
    let wants_first_layer = !rec.first_layer_taken && rec.next_layer >= 1;
    let keep_recent = rec
        .recent
        .back()
        .is_none_or(|p| super::feed::unix_now() - p.at >= cameras.settings.refresh.as_secs_f64());
    if crossed == 0 && !timed && !wants_first_layer && !keep_recent {
        return;
    }
    // One frame per layer finished, the same picture for layers quicker than the camera.
    // Layers are counted from 1: the ones finished are those before the one under way.
    let (frames, first) = match cameras.settings.timelapse {
        Timelapse::Layers => (crossed, rec.next_layer - crossed + 1),
        Timelapse::Every(_) => (usize::from(timed), rec.next_layer + 1),
        Timelapse::Off => (0, 0),
    };
    let p = match picture(cameras, printer).await {
        Ok(p) => p,
        Err(why) => {
            if frames > 0 {
                missed(rec, first, first + frames - 1, why).await;
                // Looked for again at the next period, not at every tick.
                rec.last_frame = Some(Instant::now());
            }
            return;
        }
    };
    if rec.recent.back().is_none_or(|r| r.seq != p.seq) {
        rec.recent.push_back(p.clone());
        if rec.recent.len() > BEFORE_FAILURE {
            rec.recent.pop_front();
        }
    }
    if wants_first_layer {
        rec.first_layer_taken = true;
        snapshot(rec, "first-layer", &p).await;
    }
    for layer in first..first + frames {
        timelapse_frame(rec, layer, &p).await;
    }
}

/// Layers `first..=last` have no frame, for `why`: added to the manifest (to the run
/// before when they follow it for the same cause), logged when a run starts.
async fn missed(rec: &mut Recording, first: usize, last: usize, why: NoFrame) {
    let (first, last) = (first as u32, last as u32);
    let missing = &mut rec.manifest.missing;
    match missing.last_mut() {
        Some(run) if run.why.same_cause(&why) && first <= run.last + 1 => {
            run.last = run.last.max(last);
        }
        _ => {
            tracing::warn!(printer = %rec.manifest.printer, job = %rec.job, first, last, why = ?why, "camera: no timelapse frame for these layers");
            missing.push(MissingFrames {
                first,
                last,
                why,
                at: super::feed::unix_now(),
            });
        }
    }
    write_manifest(&rec.dir, &rec.manifest).await;
}

/// The timelapse frame of `layer` (from 1); a frame that cannot be kept is missed.
async fn timelapse_frame(rec: &mut Recording, layer: usize, p: &Picture) {
    let dir = rec.dir.join(FRAMES_DIR);
    let path = dir.join(format!("{:05}.jpg", rec.frames + 1));
    let written = async {
        tokio::fs::create_dir_all(&dir).await?;
        tokio::fs::write(&path, &p.jpeg).await
    };
    match written.await {
        Ok(()) => {
            rec.frames += 1;
            rec.last_frame = Some(Instant::now());
        }
        Err(e) => {
            tracing::warn!(job = %rec.job, error = %e, file = %path.display(), "camera: cannot keep a timelapse frame");
            missed(rec, layer, layer, NoFrame::Disk).await;
        }
    }
}

async fn snapshot(rec: &mut Recording, name: &str, p: &Picture) {
    let file = format!("{name}.jpg");
    let path = rec.dir.join(&file);
    let written = async {
        tokio::fs::create_dir_all(&rec.dir).await?;
        tokio::fs::write(&path, &p.jpeg).await
    };
    if let Err(e) = written.await {
        tracing::warn!(job = %rec.job, error = %e, file = %path.display(), "camera: cannot keep a snapshot");
        return;
    }
    rec.manifest.snapshots.retain(|s| s.name != name);
    rec.manifest.snapshots.push(Snapshot {
        name: name.to_string(),
        file,
        at: p.at,
    });
    write_manifest(&rec.dir, &rec.manifest).await;
}

async fn write_manifest(dir: &Path, manifest: &JobCamera) {
    let path = dir.join(MANIFEST);
    let bytes = serde_json::to_vec_pretty(manifest).unwrap_or_default();
    let p = path.clone();
    // A camera that never gave a frame has made no folder yet; its manifest (saying the
    // layers have none) is still the job's record.
    let written = tokio::task::spawn_blocking(move || {
        if let Some(dir) = p.parent() {
            std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
        }
        crate::fsutil::write_atomic(&p, &bytes).map_err(|e| e.to_string())
    })
    .await;
    let error = match written {
        Ok(Ok(())) => return,
        Ok(Err(e)) => e,
        Err(e) => e.to_string(),
    };
    tracing::warn!(file = %path.display(), %error, "camera: cannot write the job's camera manifest");
}

/// The print is over (or left this printer): the last pictures, then the timelapse.
async fn finish(
    farm: &Farm,
    cameras: &Arc<Cameras>,
    printer: &str,
    encodes: &TaskTracker,
    mut rec: Recording,
) {
    let state = farm.store().get(&rec.job).map(|j| j.state);
    let failed = matches!(
        state,
        Some(JobState::Failed | JobState::Cancelled | JobState::Interrupted)
    );
    // The layer under way: the last one of a print done.
    let last_layer = rec.next_layer + 1;
    let took = picture(cameras, printer).await;
    if let Err(why) = took {
        if cameras.settings.timelapse != Timelapse::Off {
            missed(&mut rec, last_layer, last_layer, why).await;
        }
    }
    if let Ok(p) = took {
        if failed {
            let before: Vec<Picture> = rec
                .recent
                .iter()
                .filter(|r| r.seq != p.seq)
                .cloned()
                .collect();
            for (i, b) in before.iter().enumerate() {
                snapshot(&mut rec, &format!("before-failure-{}", i + 1), b).await;
            }
            snapshot(&mut rec, "failure", &p).await;
        } else {
            snapshot(&mut rec, "end", &p).await;
        }
        if cameras.settings.timelapse != Timelapse::Off {
            // The finished print: the last layer's frame.
            timelapse_frame(&mut rec, last_layer, &p).await;
        }
    }
    tracing::info!(printer, job = %rec.job, frames = rec.frames, "camera: print recorded; encoding its timelapse");
    let cameras = Arc::clone(cameras);
    // Off the printer's way: its next job is recorded meanwhile.
    encodes.spawn(async move {
        encode(&mut rec).await;
        timelapse::enforce_limit(cameras.root(), cameras.settings.disk_limit_bytes, &rec.job).await;
    });
}

async fn encode(rec: &mut Recording) {
    if rec.frames == 0 {
        return;
    }
    let frames = rec.dir.join(FRAMES_DIR);
    let out = rec.dir.join("timelapse.mp4");
    match timelapse::encode(&frames, &out).await {
        Ok(bytes) => {
            tracing::info!(job = %rec.job, frames = rec.frames, bytes, "camera: timelapse made");
            rec.manifest.timelapse = Some(TimelapseInfo {
                file: "timelapse.mp4".into(),
                frames: rec.frames,
                bytes,
            });
            rec.manifest.timelapse_error = None;
            let _ = tokio::fs::remove_dir_all(&frames).await;
        }
        Err(e) => {
            tracing::warn!(job = %rec.job, error = %e, "camera: no timelapse");
            rec.manifest.timelapse_error = Some(e);
        }
    }
    write_manifest(&rec.dir, &rec.manifest).await;
}

/// The timelapses a stopped or killed daemon left unmade: frames kept, no video yet. Made
/// at the next start, one at a time.
pub async fn encode_leftovers(root: &Path) {
    let Ok(mut entries) = tokio::fs::read_dir(root).await else {
        return;
    };
    while let Ok(Some(entry)) = entries.next_entry().await {
        let dir = entry.path();
        let Ok(text) = tokio::fs::read(dir.join(MANIFEST)).await else {
            continue;
        };
        let Ok(manifest) = serde_json::from_slice::<JobCamera>(&text) else {
            continue;
        };
        let frames = frames_kept(&dir).await;
        if manifest.timelapse.is_some() || frames == 0 {
            continue;
        }
        let mut rec = Recording {
            job: entry.file_name().to_string_lossy().into_owned(),
            dir,
            manifest,
            layer_starts: Vec::new(),
            next_layer: 0,
            frames,
            earlier_frames: 0,
            last_frame: None,
            first_layer_taken: true,
            recent: VecDeque::new(),
        };
        tracing::info!(job = %rec.job, frames, "camera: making the timelapse the last run left");
        encode(&mut rec).await;
    }
}

/// The timelapse frames waiting in a job's camera folder for the encoder.
async fn frames_kept(dir: &Path) -> u32 {
    let Ok(mut entries) = tokio::fs::read_dir(dir.join(FRAMES_DIR)).await else {
        return 0;
    };
    let mut n = 0;
    while let Ok(Some(_)) = entries.next_entry().await {
        n += 1;
    }
    n
}

/// Where each layer after the first starts, as command indices of the job's G-code as it
/// is streamed (the slicers' layer comments: PrusaSlicer's `;LAYER_CHANGE`, Cura's
/// `;LAYER:`); empty when it cannot be read.
async fn layer_starts_of(farm: &Farm, printer: &str, job: &str) -> Vec<usize> {
    let config = farm.config();
    let Some(p) = config.printers.iter().find(|p| p.name == printer) else {
        return Vec::new();
    };
    let (machine, firmware) = (p.machine.name.clone(), p.firmware);
    let path = {
        let store = farm.store();
        let Some(file) = store.get(job).and_then(|j| j.gcode_for(&machine)) else {
            return Vec::new();
        };
        store.job_dir(job).join(file)
    };
    tokio::task::spawn_blocking(move || layer_starts(&path, firmware))
        .await
        .unwrap_or_default()
}

fn layer_starts(path: &Path, firmware: crate::marlin::firmware::Firmware) -> Vec<usize> {
    use std::io::BufRead;
    let Ok(program) = crate::marlin::gcode::GcodeProgram::load_for(path, firmware) else {
        return Vec::new();
    };
    let Ok(file) = std::fs::File::open(path) else {
        return Vec::new();
    };
    // Line numbers (from 1) of the layer comments.
    let mut comments = Vec::new();
    for (i, line) in std::io::BufReader::new(file).split(b'\n').enumerate() {
        let Ok(line) = line else { break };
        let text = line.trim_ascii_start();
        if text.starts_with(b";LAYER_CHANGE") || text.starts_with(b";LAYER:") {
            comments.push(i + 1);
        }
    }
    // The first comment opens the first layer; each later one, a layer change.
    let mut starts = Vec::new();
    let mut command = 0;
    for &line in comments.iter().skip(1) {
        while program.source_line(command).is_some_and(|l| l <= line) {
            command += 1;
        }
        if command < program.len() {
            starts.push(command);
        }
    }
    starts
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layers_start_at_the_command_after_their_comment() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("job.gcode");
        std::fs::write(
            &path,
            "; header\nG28\n;LAYER_CHANGE\n;Z:0.2\nG1 Z0.2\nG1 X1 E1\n;LAYER_CHANGE\n\nG1 Z0.4\nG1 X2 E2\n;LAYER:2\nG1 Z0.6\nG1 X3 E3\n",
        )
        .unwrap();
        // Commands: 0 G28, 1 G1 Z0.2, 2 G1 X1, 3 G1 Z0.4, 4 G1 X2, 5 G1 Z0.6, 6 G1 X3.
        assert_eq!(
            layer_starts(&path, crate::marlin::firmware::Firmware::Marlin2),
            vec![3, 5]
        );
        assert!(layer_starts(
            &dir.path().join("none"),
            crate::marlin::firmware::Firmware::Marlin2
        )
        .is_empty());
    }
}
