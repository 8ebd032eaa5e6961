//! The farm's merge rule: chunks rendered separately, merged in any order with duplicates,
//! give exactly the single-machine render.

mod common;

use std::path::Path;
use std::sync::Mutex;
use std::time::Instant;

use common::*;
use furnace_coordinator::state::{self, accept_partial};
use furnace_coordinator::{CoordError, Coordinator};
use furnace_core::Scene;
use furnace_proto::{chunk_plan, Bundle, JobSettings, JobSpec, JobState, JobStatus};
use furnace_worker::render_chunk;

/// A persisted coordinator on `data` that checkpoints every 256 merges, without a time limit.
fn open_coordinator(data: &Path) -> Mutex<Coordinator> {
    let mut c = Coordinator::open(data).unwrap();
    c.checkpoint_interval = std::time::Duration::ZERO;
    Mutex::new(c)
}

/// Stores small.xml's files in the coordinator; returns its bundle.
fn store_small(coord: &Mutex<Coordinator>, scene: &Scene) -> Bundle {
    let (bundle, files) = Bundle::of_scene(&scenes().join("small.xml"), scene).unwrap();
    for (rel, path) in files {
        coord.lock().unwrap().store().put_file(&bundle.files[&rel], &std::fs::read(path).unwrap()).unwrap();
    }
    bundle
}

/// Stores small.xml's files in the coordinator and submits a job; returns its id.
fn submit_small(coord: &Mutex<Coordinator>, scene: &Scene, settings: JobSettings) -> String {
    let bundle = store_small(coord, scene);
    state::submit(coord, JobSpec::new(bundle, settings), None, None).unwrap().0
}

/// Leases, renders and hands in up to `limit` chunks through `accept_partial` (the path of
/// every upload, remote or in-process); returns how many.
fn render_leases(coord: &Mutex<Coordinator>, scene: &Scene, limit: usize) -> usize {
    let mut n = 0;
    while n < limit {
        let lease = coord.lock().unwrap().lease("w", Instant::now());
        let Some(l) = lease else { break };
        let (acc, stats) = render_chunk(scene, &l.chunk, l.settings.seed);
        accept_partial(coord, &l.job, l.chunk.id, l.epoch, &acc, Some(&stats), None).unwrap();
        n += 1;
    }
    n
}

/// The coordinator's merge: every chunk leased at once, rendered, handed in in reverse order
/// with every third one delivered twice (the second refused as already merged, changing
/// nothing), gives exactly the single-machine render.
#[test]
fn chunks_merged_in_any_order_with_duplicates_equal_the_local_render() {
    let scene = std::sync::Arc::new(load("small.xml", &[]));
    let settings = JobSettings {
        width: scene.film.crop_width,
        height: scene.film.crop_height,
        spp: 12,
        tile_size: 16,
        spp_per_chunk: 5,
        seed: 4,
        priority: 0,
        target_rel_error: None,
    };
    let coord = Mutex::new(Coordinator::ephemeral().unwrap());
    let job = coord.lock().unwrap().submit_scene(scene.clone(), settings.clone()).unwrap();
    let mut leases = Vec::new();
    while let Some(l) = coord.lock().unwrap().lease("w", Instant::now()) {
        leases.push(l);
    }
    assert_eq!(leases.len(), chunk_plan(&settings).len());
    for (k, l) in leases.iter().enumerate().rev() {
        let acc = render_chunk(&scene, &l.chunk, l.settings.seed).0;
        accept_partial(&coord, &job, l.chunk.id, l.epoch, &acc, None, None).unwrap();
        if k % 3 == 0 {
            let again = accept_partial(&coord, &job, l.chunk.id, l.epoch, &acc, None, None);
            assert!(matches!(again, Err(CoordError::Refused(_))), "{again:?}");
        }
    }
    let c = coord.lock().unwrap();
    assert_eq!(c.status(&job).unwrap().state, JobState::Done);
    let local = render(&scene, settings.spp, settings.seed).0.develop();
    assert!(c.image(&job).unwrap().data == local.data, "farm merge differs from the local render");
}

/// Every chunk through `accept_partial` (the path of every upload, remote or in-process), with
/// a crash after 300 merges (a checkpoint of 256 plus 44 partials on disk, 2 leases lost) and a
/// restart; then the end is undone as if the coordinator had crashed while writing the final
/// checkpoint. On restart the job is finished from what is on disk, with the same bytes.
#[test]
fn a_coordinator_restarted_mid_job_and_after_the_last_merge_finishes_the_job() {
    let dir = scratch("coord-final");
    let data = dir.join("data");
    let scene = load("small.xml", &[]);
    let coord = open_coordinator(&data);
    let settings = JobSettings {
        spp: 8,
        tile_size: 4,
        spp_per_chunk: 1,
        seed: 3,
        width: 0,
        height: 0,
        ..JobSettings::default()
    };
    let job = submit_small(&coord, &scene, settings);
    let job_dir = data.join("jobs").join(&job);
    let run = |coord: &Mutex<Coordinator>, limit| render_leases(coord, &scene, limit);
    assert_eq!(run(&coord, 300), 300);
    // Two chunks leased and never returned: lost in the crash, pending after the restart.
    coord.lock().unwrap().lease("w", Instant::now()).unwrap();
    coord.lock().unwrap().lease("w", Instant::now()).unwrap();
    assert!(job_dir.join("checkpoint").exists());
    assert_eq!(std::fs::read_dir(job_dir.join("partials")).unwrap().count(), 44);
    drop(coord);
    let coord = open_coordinator(&data);
    let s = coord.lock().unwrap().status(&job).unwrap();
    assert_eq!((s.chunks_done, s.chunks_leased), (300, 0));
    let rest = run(&coord, usize::MAX);
    assert_eq!(300 + rest as u64, s.chunks_total);
    assert_eq!(coord.lock().unwrap().status(&job).unwrap().state, JobState::Done);
    assert_eq!(
        std::fs::read_dir(job_dir.join("partials")).unwrap().count(),
        0,
        "partials left after the end"
    );
    let result = std::fs::read(job_dir.join("result.exr")).unwrap();
    let expect = render(&scene, 8, 3).0.develop();
    assert!(furnace_core::Image::read_exr(&job_dir.join("result.exr")).unwrap().data == expect.data);
    drop(coord);

    std::fs::remove_file(job_dir.join("result.exr")).unwrap();
    let db = rusqlite::Connection::open(data.join("furnace.db")).unwrap();
    db.execute("UPDATE jobs SET state = 'running' WHERE id = ?1", [&job]).unwrap();
    drop(db);
    let coord = Coordinator::open(&data).unwrap();
    assert_eq!(coord.status(&job).unwrap().state, JobState::Done);
    assert!(std::fs::read(job_dir.join("result.exr")).unwrap() == result, "result differs after restart");
    std::fs::remove_dir_all(&dir).ok();
}

/// small.xml to a target error: tiles of 4 pixels, passes of 4 spp, at most 256.
fn noise_target_settings() -> JobSettings {
    JobSettings {
        spp: 256,
        tile_size: 4,
        spp_per_chunk: 4,
        seed: 5,
        target_rel_error: Some(0.15),
        ..JobSettings::default()
    }
}

/// A noise-target job through a persisted coordinator: its tiles stop at different passes,
/// and a crash and restart mid-job (checkpoint with skipped chunks, partials replayed and
/// re-judged) gives the same bytes as the job run without interruption.
#[test]
fn a_noise_target_job_survives_a_restart_with_the_same_bytes() {
    let scene = load("small.xml", &[]);
    let settings = noise_target_settings();
    let run = |coord: &Mutex<Coordinator>, limit| render_leases(coord, &scene, limit);
    let job_of = |data: &Path| {
        let coord = open_coordinator(data);
        let job = submit_small(&coord, &scene, settings.clone());
        (coord, job)
    };
    let dir = scratch("target-restart");
    // Uninterrupted.
    let (coord, job) = job_of(&dir.join("a"));
    let total = run(&coord, usize::MAX);
    let s = coord.lock().unwrap().status(&job).unwrap();
    assert_eq!(s.state, JobState::Done);
    assert!(s.chunks_skipped > 0 && total as u64 + s.chunks_skipped == s.chunks_total, "{s:?}");
    let tiles = s.settings.tiles() as u64;
    let passes = s.chunks_total / tiles;
    assert!(
        total as u64 > tiles && (total as u64) < s.chunks_total / 2,
        "{total} chunks of {}",
        s.chunks_total
    );
    let expect = std::fs::read(dir.join("a/jobs").join(&job).join("result.exr")).unwrap();
    drop(coord);
    // Crash at 60% of the chunks (past the checkpoint after 256 merges, which records skipped
    // chunks too), two leases lost, restart, finish.
    assert!(total * 6 / 10 > 256, "{total} chunks: too few for a checkpoint before the crash");
    let (coord, job) = job_of(&dir.join("b"));
    run(&coord, total * 6 / 10);
    coord.lock().unwrap().lease("w", Instant::now());
    coord.lock().unwrap().lease("w", Instant::now());
    drop(coord);
    let coord = open_coordinator(&dir.join("b"));
    let rest = run(&coord, usize::MAX);
    assert_eq!(total * 6 / 10 + rest, total, "chunks rendered differ after the restart ({passes} passes)");
    assert_eq!(coord.lock().unwrap().status(&job).unwrap().state, JobState::Done);
    let got = std::fs::read(dir.join("b/jobs").join(&job).join("result.exr")).unwrap();
    assert!(got == expect, "noise-target result differs after a restart");
    std::fs::remove_dir_all(&dir).ok();
}

/// A noise-target job whose stored partial of a tile's pass is unusable, while the tile's
/// next pass is stored and good: the next pass waits for the one before it (it is judged after
/// it), the job ends, and its bytes are those of the job run without interruption.
#[test]
fn a_noise_target_pass_after_a_lost_one_renders_again_in_order() {
    let scene = load("small.xml", &[]);
    let settings = noise_target_settings();
    let dir = scratch("target-lost-pass");
    let coord = open_coordinator(&dir.join("a"));
    let job = submit_small(&coord, &scene, settings.clone());
    render_leases(&coord, &scene, usize::MAX);
    let tiles = coord.lock().unwrap().status(&job).unwrap().settings.tiles();
    let expect = std::fs::read(dir.join("a/jobs").join(&job).join("result.exr")).unwrap();
    drop(coord);
    // No checkpoint: every merged chunk's partial stays on disk.
    let coord = open_coordinator(&dir.join("b"));
    coord.lock().unwrap().checkpoint_interval = std::time::Duration::from_secs(3600);
    let job = submit_small(&coord, &scene, settings.clone());
    render_leases(&coord, &scene, tiles as usize * 3 / 2);
    drop(coord);
    let partials = dir.join("b/jobs").join(&job).join("partials");
    let stored = |c: u32| partials.join(format!("{c}.zst"));
    let next = (tiles..tiles * 2).find(|&c| stored(c).exists() && stored(c - tiles).exists());
    let next = next.expect("a tile with its first two passes stored");
    std::fs::write(stored(next - tiles), b"garbage").unwrap();
    let coord = open_coordinator(&dir.join("b"));
    render_leases(&coord, &scene, usize::MAX);
    let s = coord.lock().unwrap().status(&job).unwrap();
    assert_eq!(s.state, JobState::Done, "{s:?}");
    let got = std::fs::read(dir.join("b/jobs").join(&job).join("result.exr")).unwrap();
    assert!(got == expect, "result differs after a lost pass (chunk {})", next - tiles);
    std::fs::remove_dir_all(&dir).ok();
}

/// Restart never fails because of one job's files: a stored partial that is garbage, one of
/// the wrong chunk, a temporary file of an interrupted write, scene files gone, then a garbage
/// checkpoint. Each unusable file is moved to `quarantine/`, named in the job's
/// errors, and its chunks render again: the result has the same bytes; the other jobs go on.
#[test]
fn corrupt_stored_files_are_quarantined_and_their_chunks_render_again() {
    let dir = scratch("coord-quarantine");
    let data = dir.join("data");
    let scene = load("small.xml", &[]);
    let settings = JobSettings {
        spp: 4,
        tile_size: 8,
        spp_per_chunk: 2,
        seed: 5,
        width: 0,
        height: 0,
        ..JobSettings::default()
    };
    let coord = open_coordinator(&data);
    coord.lock().unwrap().checkpoint_interval = std::time::Duration::from_secs(3600);
    let job = submit_small(&coord, &scene, settings.clone());
    let other = submit_small(&coord, &scene, JobSettings { seed: 6, priority: -1, ..settings.clone() });
    let job_dir = data.join("jobs").join(&job);
    // 24 of the first job's 60 chunks: their partials are on disk, no checkpoint yet.
    assert_eq!(render_leases(&coord, &scene, 24), 24);
    drop(coord);
    let partials = job_dir.join("partials");
    let mut stored: Vec<_> = std::fs::read_dir(&partials).unwrap().map(|e| e.unwrap().path()).collect();
    stored.sort();
    assert!(stored.len() >= 4, "{} partials", stored.len());
    std::fs::write(&stored[0], b"garbage").unwrap();
    std::fs::copy(&stored[2], &stored[1]).unwrap(); // another chunk's tile
    std::fs::write(partials.join(".7.zst.tmp"), b"half a write").unwrap();
    std::fs::remove_dir_all(data.join("bundles")).unwrap();
    std::fs::remove_dir_all(data.join("files")).unwrap();
    // Both jobs' scene files gone: the coordinator starts, without them.
    let coord = open_coordinator(&data);
    for id in [&job, &other] {
        assert!(matches!(coord.lock().unwrap().status(id), Err(CoordError::Unknown(_))));
    }
    // The files come back (as a user would restore them): both jobs are back.
    store_small(&coord, &scene);
    drop(coord);
    let coord = open_coordinator(&data);
    {
        let c = coord.lock().unwrap();
        let s = c.status(&job).unwrap();
        assert_eq!(
            s.errors.iter().filter(|e| e.contains("moved to quarantine/")).count(),
            2,
            "{:?}",
            s.errors
        );
        assert!(!partials.join(".7.zst.tmp").exists());
        assert_eq!(std::fs::read_dir(job_dir.join("quarantine")).unwrap().count(), 2);
    }
    render_leases(&coord, &scene, usize::MAX);
    let c = coord.lock().unwrap();
    assert_eq!(c.status(&job).unwrap().state, JobState::Done);
    assert_eq!(c.status(&other).unwrap().state, JobState::Done);
    let expect = render(&scene, 4, 5).0.develop();
    assert!(c.image(&job).unwrap().data == expect.data, "result differs after quarantine");
    drop(c);
    drop(coord);
    // A garbage checkpoint: quarantined, every chunk in it renders again.
    let db = rusqlite::Connection::open(data.join("furnace.db")).unwrap();
    db.execute("UPDATE jobs SET state = 'running' WHERE id = ?1", [&job]).unwrap();
    drop(db);
    std::fs::write(job_dir.join("checkpoint"), [255u8; 64]).unwrap();
    std::fs::remove_file(job_dir.join("result.exr")).unwrap();
    let coord = open_coordinator(&data);
    let s = coord.lock().unwrap().status(&job).unwrap();
    assert_eq!(s.chunks_done, 0);
    assert!(s.errors.iter().any(|e| e.contains("stored checkpoint was unusable")), "{:?}", s.errors);
    render_leases(&coord, &scene, usize::MAX);
    let c = coord.lock().unwrap();
    assert_eq!(c.status(&job).unwrap().state, JobState::Done);
    assert!(c.image(&job).unwrap().data == expect.data, "result differs after a lost checkpoint");
    drop(c);
    std::fs::remove_dir_all(&dir).ok();
}

/// Stores `files` (path, bytes) in the coordinator and returns their bundle.
fn store_bundle(coord: &Mutex<Coordinator>, scene: &str, files: &[(&str, &[u8])]) -> Bundle {
    let mut bundle = Bundle { scene: scene.into(), files: Default::default() };
    for (path, bytes) in files {
        let hash = blake3::hash(bytes).to_hex().to_string();
        coord.lock().unwrap().store().put_file(&hash, bytes).unwrap();
        bundle.files.insert(path.to_string(), hash);
    }
    bundle
}

/// Issue 14: scenes were parsed under the coordinator's one lock (a 6.5 MB scene froze the
/// server for 9 minutes). Now the lock is free while a large scene loads, and a submission
/// that fails leaves nothing on disk.
#[test]
fn scenes_load_outside_the_lock_and_failed_submissions_leave_nothing() {
    let dir = scratch("coord-submit");
    let coord = std::sync::Arc::new(open_coordinator(&dir.join("data")));
    let mut xml = String::from(
        r#"<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="40"/>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>"#,
    );
    for i in 0..40_000 {
        xml.push_str(&format!(
            "<shape type=\"sphere\"><point name=\"center\" x=\"{}\" y=\"{}\" z=\"-5\"/><float name=\"radius\" value=\"0.3\"/></shape>\n",
            i % 200,
            i / 200
        ));
    }
    xml.push_str("</scene>");
    let bundle = store_bundle(&coord, "big.xml", &[("big.xml", xml.as_bytes())]);
    let spec = JobSpec::new(bundle, JobSettings { width: 0, height: 0, spp: 1, ..JobSettings::default() });
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let submitter = {
        let (coord, done) = (coord.clone(), done.clone());
        std::thread::spawn(move || {
            let t = Instant::now();
            let r = furnace_coordinator::state::submit(&coord, spec, None, None);
            done.store(true, std::sync::atomic::Ordering::SeqCst);
            (r, t.elapsed())
        })
    };
    // While it loads, the lock is taken over and over, never waited on for long.
    let (mut taken, mut longest) = (0, std::time::Duration::ZERO);
    while !done.load(std::sync::atomic::Ordering::SeqCst) {
        let t = Instant::now();
        drop(coord.lock().unwrap());
        longest = longest.max(t.elapsed());
        taken += 1;
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    let (r, took) = submitter.join().unwrap();
    r.unwrap();
    assert!(
        taken > 10 && longest < took / 4,
        "lock taken {taken} times, longest wait {longest:?} of {took:?}"
    );
    // A scene that cannot be rendered: 422, and its bundle folder is gone again.
    let bundles = || std::fs::read_dir(dir.join("data/bundles")).unwrap().count();
    let before = bundles();
    let bad = store_bundle(
        &coord,
        "a/bad.xml",
        &[("a/bad.xml", b"<scene version=\"3.0.0\"><shape type=\"teapot\"/></scene>")],
    );
    let e = furnace_coordinator::state::submit(&coord, JobSpec::new(bad, JobSettings::default()), None, None)
        .unwrap_err();
    // It names the file as the bundle does, not where this host keeps it.
    let data = dir.join("data").display().to_string();
    assert!(
        matches!(&e, CoordError::Unrenderable(m) if m.contains("teapot") && m.contains(": a/bad.xml:") && !m.contains(&data)),
        "{e:?}"
    );
    assert_eq!(bundles(), before, "a failed submission left files behind");
    // A load that ends after its request's time is up (its client answered 408) submits
    // nothing: no job appears after its client was told the submission failed.
    let scene = load("small.xml", &[]);
    let bundle = store_small(&coord, &scene);
    let spec = JobSpec::new(bundle, JobSettings { spp: 1, width: 0, height: 0, ..JobSettings::default() });
    let jobs = coord.lock().unwrap().job_ids().len();
    let late = furnace_coordinator::state::submit(&coord, spec.clone(), Some("k"), Some(Instant::now()));
    assert!(matches!(&late, Err(CoordError::TooLarge(m)) if m.contains("nothing was submitted")), "{late:?}");
    assert_eq!(coord.lock().unwrap().job_ids().len(), jobs);
    let far = Instant::now() + std::time::Duration::from_secs(60);
    assert!(furnace_coordinator::state::submit(&coord, spec, Some("k"), Some(far)).unwrap().1);
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 14: a job's memory was never released, every job ever submitted was rebuilt (scene
/// included) at each start, and there was no way to delete one. Now a finished job keeps only
/// its final status (its result is on disk), comes back after a restart without its scene,
/// and can be deleted with its files.
#[test]
fn finished_jobs_release_their_memory_restart_without_their_scene_and_can_be_deleted() {
    let dir = scratch("coord-evict");
    let data = dir.join("data");
    let scene = load("small.xml", &[]);
    let coord = open_coordinator(&data);
    let settings = JobSettings {
        spp: 4,
        tile_size: 8,
        spp_per_chunk: 2,
        seed: 9,
        width: 0,
        height: 0,
        ..JobSettings::default()
    };
    let job = submit_small(&coord, &scene, settings);
    let held = coord.lock().unwrap().held_bytes(&job).unwrap();
    assert!(held >= 48 * 40 * 96, "{held} bytes");
    let running = coord.lock().unwrap().status(&job).unwrap();
    render_leases(&coord, &scene, usize::MAX);
    let (status, image) = {
        let c = coord.lock().unwrap();
        assert_eq!(c.held_bytes(&job).unwrap(), 0, "a finished job still holds its accumulation");
        (c.status(&job).unwrap(), c.image(&job).unwrap())
    };
    assert_eq!(status.state, JobState::Done);
    assert_eq!((status.chunks_done, status.chunks_total), (running.chunks_total, running.chunks_total));
    assert!(image.data == render(&scene, 4, 9).0.develop().data);
    drop(coord);
    // Without the scene's files, a restart still brings the finished job back as it was.
    std::fs::remove_dir_all(data.join("bundles")).unwrap();
    std::fs::remove_dir_all(data.join("files")).unwrap();
    let coord = open_coordinator(&data);
    let c = coord.lock().unwrap();
    assert_eq!(c.status(&job).unwrap(), status);
    assert_eq!(c.held_bytes(&job).unwrap(), 0);
    assert!(c.image(&job).unwrap().data == image.data);
    drop(c);
    // Deleted: gone from memory and the database, with its folder (the files of its bundle
    // were removed above, as deleting would have).
    state::delete(&coord, &job).unwrap();
    assert!(!data.join("jobs").join(&job).exists());
    assert!(matches!(coord.lock().unwrap().status(&job), Err(CoordError::Unknown(_))));
    drop(coord);
    let coord = open_coordinator(&data);
    assert!(coord.lock().unwrap().job_ids().is_empty());
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 14: a cancelled job held its whole accumulation (and was rebuilt, scene included,
/// at every start). Now cancelling stores the image so far and the final status and releases
/// the rest; the preview stays; a restart brings it back without its scene.
#[test]
fn cancelled_jobs_keep_their_image_so_far_and_release_their_memory() {
    let dir = scratch("coord-cancel");
    let data = dir.join("data");
    let scene = load("small.xml", &[]);
    let coord = open_coordinator(&data);
    let settings =
        JobSettings { spp: 4, tile_size: 8, spp_per_chunk: 2, width: 0, height: 0, ..Default::default() };
    let job = submit_small(&coord, &scene, settings);
    assert_eq!(render_leases(&coord, &scene, 5), 5);
    let in_flight = coord.lock().unwrap().lease("late", Instant::now()).unwrap();
    let before = coord.lock().unwrap().image(&job).unwrap();
    furnace_coordinator::state::control(&coord, &job, "cancel").unwrap();
    let status = {
        let c = coord.lock().unwrap();
        assert_eq!(c.held_bytes(&job).unwrap(), 0, "a cancelled job still holds its accumulation");
        assert!(c.image(&job).unwrap().data == before.data, "the preview is not the image so far");
        c.status(&job).unwrap()
    };
    assert_eq!((status.state, status.chunks_done, status.chunks_leased), (JobState::Cancelled, 5, 0));
    // The lease in flight is refused, and so is resume; cancelling again changes nothing.
    let acc = render_chunk(&scene, &in_flight.chunk, in_flight.settings.seed).0;
    let late = accept_partial(&coord, &job, in_flight.chunk.id, in_flight.epoch, &acc, None, None);
    assert!(matches!(late, Err(CoordError::Refused(_))), "{late:?}");
    let resumed = furnace_coordinator::state::control(&coord, &job, "resume");
    assert!(matches!(resumed, Err(CoordError::Refused(_))), "{resumed:?}");
    let priority = state::set_priority(&coord, &job, 5);
    assert!(matches!(priority, Err(CoordError::Refused(_))), "{priority:?}");
    furnace_coordinator::state::control(&coord, &job, "cancel").unwrap();
    assert_eq!(coord.lock().unwrap().status(&job).unwrap(), status);
    drop(coord);
    std::fs::remove_dir_all(data.join("bundles")).unwrap();
    std::fs::remove_dir_all(data.join("files")).unwrap();
    let coord = open_coordinator(&data);
    let mut c = coord.lock().unwrap();
    assert_eq!(c.status(&job).unwrap(), status);
    assert!(c.image(&job).unwrap().data == before.data);
    assert!(c.lease("w", Instant::now()).is_none());
    // Restored as cancelled, not done: no result to download, counted as cancelled.
    assert!(matches!(c.result_path(&job), Err(CoordError::Refused(_))));
    assert_eq!(c.stats(Instant::now()).jobs["cancelled"], 1);
    drop(c);
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 14: a paused job held its whole accumulation for as long as it stayed paused. Now a
/// job paused with no chunk in flight for `evict_paused_after` is set aside: its checkpoint
/// is stored and its memory released; its status and preview stay; resuming loads it again
/// and it finishes with exactly the bytes of an uninterrupted render.
#[test]
fn idle_paused_jobs_are_set_aside_and_come_back_when_resumed() {
    use furnace_coordinator::state::{control, set_aside_idle};
    let dir = scratch("coord-idle");
    let scene = load("small.xml", &[]);
    let coord = open_coordinator(&dir.join("data"));
    let settings = JobSettings {
        spp: 4,
        tile_size: 8,
        spp_per_chunk: 2,
        seed: 5,
        width: 0,
        height: 0,
        ..Default::default()
    };
    let job = submit_small(&coord, &scene, settings.clone());
    assert_eq!(render_leases(&coord, &scene, 7), 7);
    let in_flight = coord.lock().unwrap().lease("slow", Instant::now()).unwrap();
    control(&coord, &job, "pause").unwrap();
    coord.lock().unwrap().evict_paused_after = std::time::Duration::ZERO;
    // A lease in flight keeps it in memory; its upload is still taken.
    set_aside_idle(&coord);
    assert!(coord.lock().unwrap().held_bytes(&job).unwrap() > 0, "set aside with a chunk in flight");
    let (acc, stats) = render_chunk(&scene, &in_flight.chunk, in_flight.settings.seed);
    accept_partial(&coord, &job, in_flight.chunk.id, in_flight.epoch, &acc, Some(&stats), None).unwrap();
    let (before, image) = {
        let c = coord.lock().unwrap();
        (c.status(&job).unwrap(), c.image(&job).unwrap())
    };
    set_aside_idle(&coord);
    {
        let c = coord.lock().unwrap();
        assert_eq!(c.held_bytes(&job).unwrap(), 0, "an idle paused job still holds its accumulation");
        let st = c.status(&job).unwrap();
        assert_eq!(st, JobStatus { samples_per_second: st.samples_per_second, ..before.clone() });
        assert_eq!(st.state, JobState::Paused);
        assert!(c.image(&job).unwrap().data == image.data, "the preview of a job set aside changed");
        assert_eq!(c.stats(Instant::now()).chunks["pending"], before.chunks_pending);
    }
    // Resumed: loaded again from its checkpoint, it goes on and ends as if never set aside
    // (and is not refused for its scene's memory, though the limit has been lowered since).
    coord.lock().unwrap().max_scene_bytes = 1;
    control(&coord, &job, "resume").unwrap();
    coord.lock().unwrap().max_scene_bytes = u64::MAX;
    assert!(coord.lock().unwrap().held_bytes(&job).unwrap() > 0);
    assert_eq!(coord.lock().unwrap().status(&job).unwrap().chunks_done, before.chunks_done);
    render_leases(&coord, &scene, usize::MAX);
    let c = coord.lock().unwrap();
    let st = c.status(&job).unwrap();
    assert_eq!(st.state, JobState::Done);
    assert!(c.image(&job).unwrap().data == render(&scene, 4, 5).0.develop().data);
    let mut expected = furnace_proto::RenderStats::default();
    let full = JobSettings { width: 48, height: 40, ..st.settings.clone() };
    for ch in chunk_plan(&full) {
        expected.merge(&render_chunk(&scene, &ch, full.seed).1);
    }
    assert_eq!(st.render_stats, expected, "statistics lost on the way");
    drop(c);
    // Cancelled while set aside: loaded again, then ended with its image so far.
    let other = submit_small(&coord, &scene, JobSettings { seed: 6, ..settings });
    render_leases(&coord, &scene, 3);
    control(&coord, &other, "pause").unwrap();
    let image = coord.lock().unwrap().image(&other).unwrap();
    set_aside_idle(&coord);
    assert_eq!(coord.lock().unwrap().held_bytes(&other).unwrap(), 0);
    control(&coord, &other, "cancel").unwrap();
    let c = coord.lock().unwrap();
    let st = c.status(&other).unwrap();
    assert_eq!((st.state, st.chunks_done), (JobState::Cancelled, 3));
    assert!(c.image(&other).unwrap().data == image.data);
    drop(c);
    std::fs::remove_dir_all(&dir).ok();
}

/// Probe of issue 14: a job whose one chunk's partial could never be uploaded (a 4096-pixel
/// tile on a large film) was accepted and rendered again forever; and jobs had no memory
/// cap together. Both are refused at submission now, naming the limit.
#[test]
fn chunks_too_big_to_upload_and_jobs_over_the_memory_cap_are_refused() {
    let dir = scratch("coord-caps");
    let scene = load("small.xml", &[]);
    let coord = open_coordinator(&dir.join("data"));
    coord.lock().unwrap().max_partial = 100_000;
    let settings = JobSettings { spp: 1, tile_size: 64, width: 0, height: 0, ..Default::default() };
    let bundle = store_small(&coord, &scene);
    let spec = |settings: &JobSettings| JobSpec::new(bundle.clone(), settings.clone());
    let e = state::submit(&coord, spec(&settings), None, None).unwrap_err();
    assert!(matches!(&e, CoordError::Unrenderable(m) if m.contains("smaller tile_size")), "{e:?}");
    let small = JobSettings { tile_size: 8, ..settings };
    coord.lock().unwrap().max_partial = 256 << 20;
    // 48 x 40 pixels hold 184 KB: room for two such jobs under 400 KB, not three.
    coord.lock().unwrap().max_job_bytes = 400_000;
    let submit = |s: &JobSettings| state::submit(&coord, spec(s), None, None);
    submit(&small).unwrap();
    submit(&JobSettings { seed: 1, ..small.clone() }).unwrap();
    let e = submit(&JobSettings { seed: 2, ..small.clone() }).unwrap_err();
    assert!(matches!(&e, CoordError::Busy(m) if m.contains("--max-job-memory-gb")), "{e:?}");
    assert_eq!(coord.lock().unwrap().job_ids().len(), 2);
    // A scene that needs more memory to load than a scene may take is refused, naming the
    // setting; the coordinator builds no BVH, yet counts it.
    coord.lock().unwrap().max_job_bytes = 8 << 30;
    coord.lock().unwrap().max_scene_bytes = scene.load_estimate - 1;
    let e = submit(&JobSettings { seed: 3, ..small.clone() }).unwrap_err();
    assert!(matches!(&e, CoordError::Unrenderable(m) if m.contains("--max-scene-memory-mb")), "{e:?}");
    coord.lock().unwrap().max_scene_bytes = scene.load_estimate;
    submit(&JobSettings { seed: 3, ..small }).unwrap();
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 14: render statistics stayed with the worker (the HTTP upload dropped them). Each
/// partial now carries its chunk's, the job's status sums them exactly, and a restart keeps
/// them: from the stored partials, and from the checkpoint once the job is done.
#[test]
fn render_statistics_travel_with_partials_and_survive_restarts() {
    let dir = scratch("coord-stats");
    let data = dir.join("data");
    let scene = load("small.xml", &[]);
    let settings = JobSettings {
        spp: 4,
        tile_size: 8,
        spp_per_chunk: 2,
        seed: 3,
        width: 0,
        height: 0,
        ..Default::default()
    };
    let mut expected = furnace_proto::RenderStats::default();
    let full =
        JobSettings { width: scene.film.crop_width, height: scene.film.crop_height, ..settings.clone() };
    for c in chunk_plan(&full) {
        expected.merge(&render_chunk(&scene, &c, full.seed).1);
    }
    assert!(expected.rays > 0 && expected.samples == 48 * 40 * 4);
    let coord = open_coordinator(&data);
    let job = submit_small(&coord, &scene, settings);
    render_leases(&coord, &scene, 7);
    let mid = coord.lock().unwrap().status(&job).unwrap().render_stats;
    assert!(mid.samples > 0 && mid.samples < expected.samples, "{mid:?}");
    drop(coord);
    let coord = open_coordinator(&data);
    assert_eq!(coord.lock().unwrap().status(&job).unwrap().render_stats, mid, "lost at restart");
    render_leases(&coord, &scene, usize::MAX);
    assert_eq!(coord.lock().unwrap().status(&job).unwrap().render_stats, expected);
    drop(coord);
    let coord = open_coordinator(&data);
    assert_eq!(coord.lock().unwrap().status(&job).unwrap().render_stats, expected);
    drop(coord);
    std::fs::remove_dir_all(&dir).ok();
}

/// Concurrent submissions of one bundle (a client's retry is enough) each lay it out in a
/// folder of their own: the stored files stay intact and every submission gets a job.
#[test]
fn concurrent_submissions_of_one_bundle_leave_its_files_intact() {
    let dir = scratch("coord-concurrent");
    let coord = std::sync::Arc::new(open_coordinator(&dir.join("data")));
    let scene = load("small.xml", &[]);
    let bundle = store_small(&coord, &scene);
    let settings = JobSettings { width: 0, height: 0, spp: 1, ..JobSettings::default() };
    let threads: Vec<_> = (0..4)
        .map(|_| {
            let (coord, spec) = (coord.clone(), JobSpec::new(bundle.clone(), settings.clone()));
            std::thread::spawn(move || furnace_coordinator::state::submit(&coord, spec, None, None))
        })
        .collect();
    for t in threads {
        t.join().unwrap().unwrap();
    }
    for hash in bundle.files.values() {
        let bytes = coord.lock().unwrap().store().file(hash).unwrap();
        assert_eq!(blake3::hash(&bytes).to_hex().as_str(), hash, "a stored file changed");
    }
    let leftovers = std::fs::read_dir(dir.join("data/bundles"))
        .unwrap()
        .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().ends_with(".tmp"));
    assert_eq!(leftovers.count(), 0);
    assert_eq!(coord.lock().unwrap().job_ids().len(), 4);
    std::fs::remove_dir_all(&dir).ok();
}

/// A data folder from before idempotency keys were tied to their spec opens, and takes jobs.
#[test]
fn a_database_from_before_request_hashes_is_migrated() {
    let dir = scratch("coord-migrate");
    let data = dir.join("data");
    std::fs::create_dir_all(&data).unwrap();
    let db = rusqlite::Connection::open(data.join("furnace.db")).unwrap();
    db.execute_batch(
        "CREATE TABLE jobs (id TEXT PRIMARY KEY, spec TEXT NOT NULL, state TEXT NOT NULL,
             idempotency_key TEXT UNIQUE, created INTEGER NOT NULL);
         CREATE TABLE meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);",
    )
    .unwrap();
    drop(db);
    let coord = open_coordinator(&data);
    let scene = load("small.xml", &[]);
    let settings = JobSettings { width: 0, height: 0, spp: 1, ..JobSettings::default() };
    let job = submit_small(&coord, &scene, settings);
    assert_eq!(coord.lock().unwrap().status(&job).unwrap().state, JobState::Queued);
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 14: a final checkpoint that failed (a full disk) left the job running at 100% until a
/// restart. The server's timer tries it again; here `retry_checkpoints` is called by hand.
#[test]
fn a_failed_final_checkpoint_is_tried_again() {
    let dir = scratch("coord-retry");
    let data = dir.join("data");
    let scene = load("small.xml", &[]);
    let coord = open_coordinator(&data);
    coord.lock().unwrap().checkpoint_retry = std::time::Duration::ZERO;
    let settings = JobSettings {
        spp: 2,
        tile_size: 16,
        spp_per_chunk: 2,
        seed: 2,
        width: 0,
        height: 0,
        ..JobSettings::default()
    };
    let job = submit_small(&coord, &scene, settings);
    // A folder where the checkpoint goes: renaming the written file onto it fails.
    let blocker = data.join("jobs").join(&job).join("checkpoint");
    std::fs::create_dir_all(blocker.join("x")).unwrap();
    let n = coord.lock().unwrap().status(&job).unwrap().chunks_total as usize;
    // The last upload's checkpoint fails, so its accept_partial fails.
    for _ in 0..n {
        let l = coord.lock().unwrap().lease("w", Instant::now()).unwrap();
        let acc = render_chunk(&scene, &l.chunk, l.settings.seed).0;
        let _ = accept_partial(&coord, &l.job, l.chunk.id, l.epoch, &acc, None, None);
    }
    let s = coord.lock().unwrap().status(&job).unwrap();
    assert_eq!((s.state, s.chunks_done), (JobState::Running, s.chunks_total));
    assert!(s.errors.iter().any(|e| e.contains("checkpoint failed")), "{:?}", s.errors);
    furnace_coordinator::state::retry_checkpoints(&coord);
    assert_eq!(
        coord.lock().unwrap().status(&job).unwrap().state,
        JobState::Running,
        "the disk is still full"
    );
    let tmp = std::fs::read_dir(data.join("jobs").join(&job)).unwrap().flatten();
    assert_eq!(
        tmp.filter(|e| e.file_name().to_string_lossy().ends_with(".tmp")).count(),
        0,
        "temporary files left"
    );
    std::fs::remove_dir_all(&blocker).unwrap();
    furnace_coordinator::state::retry_checkpoints(&coord);
    let c = coord.lock().unwrap();
    assert_eq!(c.status(&job).unwrap().state, JobState::Done);
    assert!(c.image(&job).unwrap().data == render(&scene, 2, 2).0.develop().data);
    drop(c);
    std::fs::remove_dir_all(&dir).ok();
}

/// A job left out at a start (its scene files gone) can still be deleted; ids that are not
/// job ids (`..`) are not found.
#[test]
fn a_job_left_out_at_start_can_be_deleted() {
    let dir = scratch("coord-delete");
    let data = dir.join("data");
    let scene = load("small.xml", &[]);
    let coord = open_coordinator(&data);
    let job =
        submit_small(&coord, &scene, JobSettings { width: 0, height: 0, spp: 1, ..JobSettings::default() });
    drop(coord);
    std::fs::remove_dir_all(data.join("bundles")).unwrap();
    std::fs::remove_dir_all(data.join("files")).unwrap();
    let coord = open_coordinator(&data);
    assert!(matches!(coord.lock().unwrap().status(&job), Err(CoordError::Unknown(_))));
    for bad in ["..", "", "a/b"] {
        assert!(matches!(state::delete(&coord, bad), Err(CoordError::Unknown(_))), "{bad:?}");
    }
    assert!(data.join("jobs").join(&job).is_dir());
    state::delete(&coord, &job).unwrap();
    assert!(!data.join("jobs").join(&job).exists());
    assert!(matches!(state::delete(&coord, &job), Err(CoordError::Unknown(_))));
    std::fs::remove_dir_all(&dir).ok();
}

/// Deleting a job removes its bundle's stored files only when no other job uses them.
#[test]
fn deleting_a_job_keeps_the_files_other_jobs_use() {
    let dir = scratch("coord-gc");
    let scene = load("small.xml", &[]);
    let coord = open_coordinator(&dir.join("data"));
    let settings = JobSettings { width: 0, height: 0, spp: 1, ..JobSettings::default() };
    let a = submit_small(&coord, &scene, settings.clone());
    let b = submit_small(&coord, &scene, JobSettings { seed: 1, ..settings });
    let (bundle, _) = Bundle::of_scene(&scenes().join("small.xml"), &scene).unwrap();
    let files = || bundle.files.values().filter(|h| dir.join("data/files").join(h).is_file()).count();
    let laid_out = dir.join("data/bundles").join(bundle.hash());
    state::delete(&coord, &a).unwrap();
    assert!(!dir.join("data/jobs").join(&a).exists());
    assert_eq!(files(), bundle.files.len(), "b still uses the files");
    assert!(laid_out.is_dir() && dir.join("data/jobs").join(&b).is_dir());
    state::delete(&coord, &b).unwrap();
    assert_eq!(files(), 0);
    assert!(!laid_out.exists() && !dir.join("data/jobs").join(&b).exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// Stores the files of every frame of `scene` (frames.xml with `frame` = each of `frames`) in
/// the coordinator; returns their union bundle.
fn store_frames(coord: &Mutex<Coordinator>, frames: &[u32]) -> Bundle {
    let mut union = Bundle { scene: "frames.xml".into(), files: Default::default() };
    for n in frames {
        let scene = load("frames.xml", &[("frame", &n.to_string())]);
        let (bundle, files) = Bundle::of_scene(&scenes().join("frames.xml"), &scene).unwrap();
        for (rel, path) in files {
            coord
                .lock()
                .unwrap()
                .store()
                .put_file(&bundle.files[&rel], &std::fs::read(path).unwrap())
                .unwrap();
        }
        union.files.extend(bundle.files);
    }
    union
}

/// Issue 18: a frame range is one job whose frames are jobs of their own: handed out frame by
/// frame, each merged into its own image (equal to rendering that frame alone), listed as one
/// job with a status per frame, restored as one after a restart (its idempotency key still
/// naming it), and paused, resumed and deleted as one.
#[test]
fn a_frame_range_is_one_job_rendered_frame_by_frame() {
    let dir = scratch("coord-frames");
    let data = dir.join("data");
    let coord = open_coordinator(&data);
    let range = furnace_proto::FrameRange::parse("0-20:10").unwrap();
    let numbers: Vec<u32> = range.numbers().collect();
    let bundle = store_frames(&coord, &numbers);
    let settings = JobSettings {
        spp: 4,
        tile_size: 16,
        spp_per_chunk: 2,
        seed: 3,
        width: 0,
        height: 0,
        ..Default::default()
    };
    let spec = JobSpec { frames: Some(range), ..JobSpec::new(bundle.clone(), settings.clone()) };
    let (job, created) = state::submit(&coord, spec.clone(), Some("anim"), None).unwrap();
    assert!(created);
    // A spec may not claim to be another job's frame.
    let forged = JobSpec {
        frame_of: Some(furnace_proto::FrameOf { job: job.clone(), frame: 0 }),
        ..JobSpec::new(bundle.clone(), settings.clone())
    };
    let e = state::submit(&coord, forged, None, None).unwrap_err();
    assert!(matches!(&e, CoordError::Invalid(m) if m.contains("frame_of")), "{e:?}");
    {
        let c = coord.lock().unwrap();
        assert_eq!(c.job_ids(), vec![job.clone()], "the frames are listed as one job");
        let st = c.status(&job).unwrap();
        assert_eq!(st.frames.iter().map(|f| f.frame).collect::<Vec<_>>(), numbers);
        // 40 x 32 in 16-pixel tiles, 2 passes: 12 chunks a frame.
        assert_eq!((st.chunks_total, st.samples_total), (36, 3 * 40 * 32 * 4));
        assert_eq!(st.state, JobState::Queued);
        let e = c.result_path(&job).unwrap_err();
        assert!(e.to_string().contains("/frames/{n}/result.exr"), "{e}");
        assert!(matches!(c.frame_job(&job, 5), Err(CoordError::Unknown(_))));
    }
    // Frame 0's chunks go first, then frame 10's; a restart meanwhile changes nothing.
    let frame_of = |l: &furnace_proto::Lease| l.job.rsplit('-').next().unwrap().parse::<u32>().unwrap();
    let mut order = Vec::new();
    let hand_in = |coord: &Mutex<Coordinator>, limit: usize, order: &mut Vec<u32>| {
        for _ in 0..limit {
            let Some(l) = coord.lock().unwrap().lease("w", Instant::now()) else { break };
            order.push(frame_of(&l));
            let defines: Vec<(&str, &str)> =
                l.defines.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
            let scene = load("frames.xml", &defines);
            let (acc, stats) = render_chunk(&scene, &l.chunk, l.settings.seed);
            accept_partial(coord, &l.job, l.chunk.id, l.epoch, &acc, Some(&stats), None).unwrap();
        }
    };
    hand_in(&coord, 15, &mut order);
    {
        let c = coord.lock().unwrap();
        let st = c.status(&job).unwrap();
        assert_eq!(st.state, JobState::Running);
        assert_eq!(st.frames[0].state, JobState::Done);
        assert_eq!((st.frames[1].chunks_done, st.frames[2].chunks_done), (3, 0));
        assert_eq!(st.chunks_done, 15);
        // The progress bar's poll: status's counts without the rest.
        assert_eq!(c.progress(&job).unwrap(), (st.samples_done, st.samples_total));
        assert!(st.samples_done > 0 && st.samples_done < st.samples_total);
        let frame = c.frame_job(&job, numbers[1]).unwrap();
        let fs = c.status(&frame).unwrap();
        assert_eq!(c.progress(&frame).unwrap(), (fs.samples_done, fs.samples_total));
        assert!(c.progress("no-such-job").is_err());
    }
    drop(coord);
    let coord = open_coordinator(&data);
    assert_eq!(state::submit(&coord, spec.clone(), Some("anim"), None).unwrap(), (job.clone(), false));
    state::control(&coord, &job, "pause").unwrap();
    assert!(
        coord.lock().unwrap().lease("w", Instant::now()).is_none(),
        "a paused frame range hands out nothing"
    );
    assert_eq!(coord.lock().unwrap().status(&job).unwrap().state, JobState::Paused);
    state::control(&coord, &job, "resume").unwrap();
    hand_in(&coord, usize::MAX, &mut order);
    assert!(order.windows(2).all(|w| w[0] <= w[1]), "frames out of order: {order:?}");
    assert_eq!(order.len(), 36);
    let c = coord.lock().unwrap();
    let st = c.status(&job).unwrap();
    assert_eq!(st.state, JobState::Done);
    assert!(st.frames.iter().all(|f| f.state == JobState::Done && f.samples_done == 40 * 32 * 4));
    assert_eq!(c.progress(&job).unwrap(), (st.samples_done, st.samples_done));
    for n in numbers {
        // Each frame's result is what rendering that frame alone gives.
        let frame = c.frame_job(&job, n).unwrap();
        let scene = load("frames.xml", &[("frame", &n.to_string())]);
        let alone = render(&scene, 4, 3).0.develop();
        let path = c.result_path(&frame).unwrap();
        let got = furnace_core::Image::read_exr(&path).unwrap();
        assert!(got.data == alone.data, "frame {n} differs from its render alone");
    }
    drop(c);
    let e = state::control(&coord, &job, "cancel").unwrap_err();
    assert!(matches!(&e, CoordError::Refused(m) if m.contains("is done")), "{e:?}");
    state::delete(&coord, &job).unwrap();
    assert!(coord.lock().unwrap().job_ids().is_empty());
    assert!(std::fs::read_dir(data.join("jobs")).unwrap().next().is_none(), "a frame's folder is left");
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 18, hardened: what a frame range may cost the coordinator. A range whose frames would
/// hold more than the job memory limit is refused after its first frame, not after making them
/// all; a noise-target range opens at most `MAX_OPEN_FRAMES` frames at once (each holds an
/// image); `####` frames each carry their own scene file, not every frame's; a frame cancelled
/// alone leaves the others rendering, and frames cancelled before they began store no image;
/// a restart keeps no frame's scene in memory before a worker reaches it.
#[test]
fn frame_ranges_are_bounded_in_memory_and_cancel_cheaply() {
    let dir = scratch("coord-frames-bounded");
    let data = dir.join("data");
    let coord = open_coordinator(&data);
    let bundle = store_frames(&coord, &[0]);
    let settings =
        JobSettings { spp: 1024, tile_size: 16, spp_per_chunk: 1, width: 0, height: 0, ..Default::default() };
    // 6 tiles x 1024 passes a frame: about 0.7 MB of chunk plan a frame; 10,000 frames would
    // be 7 GB. Refused against a 256 MB limit, and at once.
    coord.lock().unwrap().max_job_bytes = 256 << 20;
    let huge = JobSpec {
        frames: Some(furnace_proto::FrameRange::parse("0-9999").unwrap()),
        ..JobSpec::new(bundle.clone(), settings.clone())
    };
    let t = Instant::now();
    let e = state::submit(&coord, huge, None, None).unwrap_err();
    assert!(matches!(&e, CoordError::TooLarge(m) if m.contains("10000 frames")), "{e:?}");
    assert!(t.elapsed().as_secs_f64() < 10.0, "refused only after {:?}", t.elapsed());
    assert!(coord.lock().unwrap().job_ids().is_empty());
    coord.lock().unwrap().max_job_bytes = 8 << 30;

    // A range out of time says how far its check came.
    let late = JobSpec {
        frames: Some(furnace_proto::FrameRange::parse("0-2").unwrap()),
        ..JobSpec::new(bundle.clone(), settings.clone())
    };
    let e = state::submit(&coord, late, None, Some(Instant::now())).unwrap_err();
    assert!(
        matches!(&e, CoordError::TooLarge(m) if m.contains("the 3 frames") && m.contains("frame 0: the request's time ran out")),
        "{e:?}"
    );

    // A frame every worker has failed on too often holds no open slot: with one worker that
    // fails everything, the range goes on frame after frame instead of stopping at frame 3.
    let broken = JobSpec {
        frames: Some(furnace_proto::FrameRange::parse("0-4").unwrap()),
        ..JobSpec::new(bundle.clone(), JobSettings { spp: 2, spp_per_chunk: 2, ..settings.clone() })
    };
    let (broken, _) = state::submit(&coord, broken, None, None).unwrap();
    let mut reached = 0;
    for _ in 0..100 {
        let mut c = coord.lock().unwrap();
        let Some(l) = c.lease("w", Instant::now()) else { break };
        reached = reached.max(l.job.rsplit('-').next().unwrap().parse::<u32>().unwrap());
        c.fail(&l.job, l.chunk.id, l.epoch, "broken").unwrap();
    }
    assert_eq!(reached, 4, "the range stopped at frame {reached}");
    state::delete(&coord, &broken).unwrap();
    // (Deleting it removed the files no other job used.)
    assert_eq!(store_frames(&coord, &[0]), bundle);

    // A noise-target range: each frame's queue holds only its first pass until it is judged.
    let noisy = JobSettings { spp: 8, spp_per_chunk: 2, target_rel_error: Some(1e-6), ..settings.clone() };
    let spec = JobSpec {
        frames: Some(furnace_proto::FrameRange::parse("0-7").unwrap()),
        ..JobSpec::new(bundle.clone(), noisy)
    };
    let (job, _) = state::submit(&coord, spec, None, None).unwrap();
    let mut leased = std::collections::BTreeSet::new();
    while let Some(l) = coord.lock().unwrap().lease("w", Instant::now()) {
        leased.insert(l.job.clone());
    }
    let frames: std::collections::BTreeSet<&str> =
        leased.iter().map(|j| j.rsplit('-').next().unwrap()).collect();
    assert_eq!(frames.len(), state::MAX_OPEN_FRAMES, "frames opened: {frames:?}");
    assert_eq!(frames, ["0", "1", "2"].into_iter().collect());

    // Frame 1 cancelled alone: the job goes on; then the whole job is cancelled.
    let frame1 = coord.lock().unwrap().frame_job(&job, 1).unwrap();
    state::control(&coord, &frame1, "cancel").unwrap();
    let st = coord.lock().unwrap().status(&job).unwrap();
    assert_eq!(st.state, JobState::Running, "one cancelled frame ended the job");
    assert_eq!(st.frames[1].state, JobState::Cancelled);
    let next = coord.lock().unwrap().lease("w", Instant::now()).expect("frame 3 may start now");
    assert!(next.job.ends_with("-3"), "{}", next.job);
    state::control(&coord, &job, "cancel").unwrap();
    let c = coord.lock().unwrap();
    assert_eq!(c.status(&job).unwrap().state, JobState::Cancelled);
    for n in 4..=7 {
        let frame = c.frame_job(&job, n).unwrap();
        assert!(c.store().checkpoint(&frame).is_none(), "frame {n} never began but stored an image");
    }
    drop(c);
    drop(coord);
    let coord = Mutex::new(Coordinator::open_with(&data, true).unwrap());
    {
        let c = coord.lock().unwrap();
        let st = c.status(&job).unwrap();
        assert_eq!(st.state, JobState::Cancelled);
        assert!(st.frames.iter().all(|f| f.state == JobState::Cancelled), "{:?}", st.frames);
        for n in 4..=7 {
            // Restored from its status alone: not loaded again, no image written at start.
            let frame = c.frame_job(&job, n).unwrap();
            assert!(c.store().checkpoint(&frame).is_none(), "frame {n}: an image was written at restart");
            // Its preview is black, not an error.
            let image = c.image(&frame).unwrap();
            assert_eq!((image.width, image.height), (40, 32));
            assert!(image.data.iter().all(|v| v.max_element() == 0.0 && v.min_element() == 0.0));
        }
    }

    // Frames of `####` files: each frame's bundle holds its own scene file only.
    let folder = dir.join("anim");
    std::fs::create_dir_all(folder.join("assets")).unwrap();
    for asset in ["quad.obj", "checker.png"] {
        std::fs::copy(scenes().join("assets").join(asset), folder.join("assets").join(asset)).unwrap();
    }
    let mut anim = Bundle { scene: "anim_##.xml".into(), files: Default::default() };
    let xml = std::fs::read_to_string(scenes().join("frames.xml")).unwrap();
    let default = "<default name=\"frame\" value=\"0\"/>";
    assert!(xml.contains(default));
    for n in [0u32, 1, 2] {
        let path = folder.join(format!("anim_{n:02}.xml"));
        std::fs::write(&path, xml.replace(default, &format!("<default name=\"frame\" value=\"{n}\"/>")))
            .unwrap();
        let (b, local) = Bundle::of_scene(&path, &Scene::load(&path, &[]).unwrap()).unwrap();
        for (rel, p) in local {
            coord.lock().unwrap().store().put_file(&b.files[&rel], &std::fs::read(p).unwrap()).unwrap();
        }
        anim.files.extend(b.files);
    }
    let spec = JobSpec {
        frames: Some(furnace_proto::FrameRange::parse("0-2").unwrap()),
        ..JobSpec::new(anim, JobSettings { spp: 2, spp_per_chunk: 2, ..settings })
    };
    let (job, _) = state::submit(&coord, spec, None, None).unwrap();
    let mut seen = std::collections::BTreeSet::new();
    loop {
        let lease = coord.lock().unwrap().lease("w", Instant::now());
        let Some(l) = lease else { break };
        if !seen.insert(l.bundle_hash.clone()) {
            continue;
        }
        let manifest =
            String::from_utf8(coord.lock().unwrap().bundle_manifest(&l.bundle_hash).unwrap()).unwrap();
        let n: u32 = l.job.rsplit('-').next().unwrap().parse().unwrap();
        for m in [0u32, 1, 2] {
            let name = format!("anim_{m:02}.xml");
            assert_eq!(manifest.contains(&name), m == n, "frame {n}'s bundle and {name}: {manifest}");
        }
        assert!(manifest.contains("checker.png"), "the shared texture: {manifest}");
        // No frame's scene is held before a worker asks for it.
        assert!(coord.lock().unwrap().job_scene(&l.job).is_none() || n == 0);
    }
    assert_eq!(seen.len(), 3, "frames of job {job}");
    drop(coord);
    let coord = Mutex::new(Coordinator::open_with(&data, true).unwrap());
    let c = coord.lock().unwrap();
    for n in 0..3 {
        let frame = c.frame_job(&job, n).unwrap();
        assert!(c.job_scene(&frame).is_none(), "frame {n}'s scene loaded at restart");
    }
    drop(c);
    std::fs::remove_dir_all(&dir).ok();
}
