//! The ALOHA export's memory is the episode's steps and a window of frames, not the episode's
//! file: one episode with a raw 480x640 camera (PNG in the store) is written back with a peak
//! heap far below its frames. The previous writer, `hdf5-pure`'s `FileBuilder`, held the file
//! (1,481 MB peak RSS for a 1.1 GB episode; 58 MB streamed).
//!
//! Its own test binary: the allocator counts the whole process.
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

use export::aloha;
use h5stream::{Attr, Group, Writer};
use ingest::{ingest, IngestOptions};
use store::test_support::{peak_heap_while, CountingAlloc};
use store::{select, Selection, Store, StoreConfig};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

const T: u64 = 120;
const H: u64 = 480;
const W: u64 = 640;

/// Frame `t`: flat colour blocks (PNG makes them small, as it does a camera's flat background).
fn frame(t: u64) -> Vec<u8> {
    let mut f = vec![0u8; (H * W * 3) as usize];
    for (i, px) in f.chunks_mut(3).enumerate() {
        let (y, x) = (i as u64 / W, i as u64 % W);
        px.copy_from_slice(&[(x / 64 * 20 + t) as u8, (y / 48 * 20) as u8, ((x + y + t) / 128 * 30) as u8]);
    }
    f
}

/// An ALOHA episode file: qpos, qvel, action (T x 14 float32), one raw camera, `@sim`.
fn write_source(path: &std::path::Path) {
    let mut w = Writer::create(path).unwrap();
    let arm: Vec<f32> = (0..T * 14).map(|i| (i as f32 * 0.01).sin()).collect();
    let mut images = Group::default();
    let mut cam = w.stream::<u8>(&[T, H, W, 3]).unwrap();
    for t in 0..T {
        cam.write(&frame(t)).unwrap();
    }
    images.link("cam_high", cam.finish().unwrap());
    let mut obs = Group::default();
    obs.link("qpos", w.dataset(&[T, 14], &arm).unwrap());
    obs.link("qvel", w.dataset(&[T, 14], &arm).unwrap());
    obs.link("images", w.group(images).unwrap());
    let mut root = Group::default();
    root.link("observations", w.group(obs).unwrap());
    root.link("action", w.dataset(&[T, 14], &arm).unwrap());
    root.attr("sim", Attr::number(0i8));
    w.finish(root).unwrap();
}

#[test]
fn aloha_export_peak_is_a_window_not_the_episode() {
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let src = tmp.path().join("src");
    std::fs::create_dir(&src).unwrap();
    write_source(&src.join("episode_0.hdf5"));
    let store = rt.block_on(Store::open(&StoreConfig::local(tmp.path().join("store")))).unwrap();
    let opts = IngestOptions { policy: "act".into(), checkpoint: "c0".into(), ..Default::default() };
    rt.block_on(ingest(&store, &src, &opts)).unwrap();
    let sel = rt.block_on(select(&store, &Selection::default())).unwrap();
    let out = tmp.path().join("out");
    let (peak, report) = peak_heap_while(|| rt.block_on(aloha::export(&store, &sel, &out, None)).unwrap());
    assert_eq!(report.episodes, 1);
    let frames = (T * H * W * 3) as usize;
    let file = std::fs::metadata(out.join("episode_0.hdf5")).unwrap().len() as usize;
    eprintln!(
        "ALOHA export of {:.1} MB of frames ({:.1} MB file): peak heap {:.1} MB",
        frames as f64 / 1e6,
        file as f64 / 1e6,
        peak as f64 / 1e6
    );
    assert!(file > frames, "the file ({file} bytes) holds the frames ({frames})");
    // The steps (PNG bytes) and an 8 MiB window of decoded frames (34 MB with a 16 MiB window),
    // not the 110 MB of frames.
    assert!(peak < frames / 2, "peak heap {peak} bytes for {frames} bytes of frames");
    // The frames came back as they went in.
    let f = hdf5_pure::File::open(out.join("episode_0.hdf5")).unwrap();
    let cam = f.dataset("observations/images/cam_high").unwrap();
    assert_eq!(cam.shape().unwrap(), vec![T, H, W, 3]);
    let back = cam.read_u8().unwrap();
    for t in [0, T / 2, T - 1] {
        let n = (H * W * 3) as usize;
        assert!(back[t as usize * n..(t as usize + 1) * n] == frame(t)[..], "frame {t}");
    }
}
