//! `--images video`: a robomimic file with two cameras (84×84 and 64×96, a rendered scene whose
//! objects move) ingested into a real temporary store. Each episode's cameras become media
//! objects (H.264 MP4) listed as video cameras; every frame, decoded with OpenH264 from the
//! stored object and again independently with FFmpeg (PyAV), is within a PSNR bound of the
//! original; the read path serves a frame decoded (PNG). The source is identified by its
//! content, so the same file ingested again (with either `--images`) is already in the store.

use std::path::Path;

use hdf5_pure::{AttrValue, FileBuilder};
use ingest::{ingest, ImageStorage, IngestOptions};
use store::{CameraKind, EpisodeFilter, Store, StoreConfig};

const STEPS: usize = 45;
const DEMOS: usize = 2;
/// The cameras: name, height, width.
const CAMERAS: [(&str, usize, usize); 2] =
    [("agentview_image", 84, 84), ("robot0_eye_in_hand_image", 64, 96)];
/// Frames must come back at least this close (dB). This scene is harsher than a camera (hard
/// saturated edges, a 6-pixel checker): 4:2:0 chroma costs it most; real renders: README.
const MIN_PSNR_DB: f64 = 25.0;

/// Frame `t` of a camera of demo `d`: a shaded background, a box sliding across, a disc growing,
/// texture on the table: what a robot camera sees, with edges and gradients.
fn frame(d: usize, cam: usize, t: usize, h: usize, w: usize) -> Vec<u8> {
    let mut px = vec![0u8; h * w * 3];
    let (bx, by) = ((4 + t * 2 + d * 7) % (w - 16), h / 3 + cam * 5);
    let (cx, cy, r) = (w as f64 / 2.0, h as f64 * 0.7, 4.0 + (t % 20) as f64 * 0.8);
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) * 3;
            let mut c = [(40 + y * 120 / h) as u8, (60 + x * 80 / w) as u8, (110 + 30 * d + cam * 20) as u8];
            if y > h * 3 / 4 && (x / 6 + y / 6) % 2 == 0 {
                c = [150, 130, 100]; // the table's checker texture
            }
            if (bx..bx + 14).contains(&x) && (by..by + 12).contains(&y) {
                c = [220, 50, 40];
            }
            if ((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)).sqrt() < r {
                c = [240, 210, 40];
            }
            px[i..i + 3].copy_from_slice(&c);
        }
    }
    px
}

fn write_robomimic(path: &Path) {
    let mut b = FileBuilder::new();
    let mut data = b.create_group("data");
    for d in 0..DEMOS {
        let mut g = data.create_group(&format!("demo_{d}"));
        let mut obs = g.create_group("obs");
        let pos: Vec<f64> = (0..STEPS * 3).map(|k| k as f64 * 0.01).collect();
        obs.create_dataset("robot0_eef_pos").with_f64_data(&pos).with_shape(&[STEPS as u64, 3]);
        for (c, (name, h, w)) in CAMERAS.iter().enumerate() {
            let frames: Vec<u8> = (0..STEPS).flat_map(|t| frame(d, c, t, *h, *w)).collect();
            obs.create_dataset(name).with_u8_data(&frames).with_shape(&[
                STEPS as u64,
                *h as u64,
                *w as u64,
                3,
            ]);
        }
        g.add_group(obs.finish());
        let act: Vec<f64> = (0..STEPS * 7).map(|k| (k % 13) as f64 / 13.0).collect();
        g.create_dataset("actions").with_f64_data(&act).with_shape(&[STEPS as u64, 7]);
        g.create_dataset("rewards").with_f64_data(&vec![0.0; STEPS]);
        let dones: Vec<i64> = (0..STEPS).map(|t| (t + 1 == STEPS) as i64).collect();
        g.create_dataset("dones").with_i64_data(&dones);
        g.set_attr("num_samples", AttrValue::I64(STEPS as i64));
        data.add_group(g.finish());
    }
    data.set_attr("total", AttrValue::I64((DEMOS * STEPS) as i64));
    data.set_attr(
        "env_args",
        AttrValue::String(r#"{"env_name": "Lift", "env_kwargs": {"control_freq": 20}}"#.into()),
    );
    b.add_group(data.finish());
    b.write(path).unwrap();
}

fn demo_of(source_name: &str) -> usize {
    source_name.trim_start_matches("demo_").parse().expect("demo_<i>")
}

fn png_rgb(png_bytes: &[u8]) -> (usize, usize, Vec<u8>) {
    ingest::video::png_to_rgb(png_bytes).expect("a PNG").expect("8-bit")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn robomimic_cameras_as_video() {
    let tmp = tempfile::tempdir().unwrap();
    let h5 = tmp.path().join("two_cameras.hdf5");
    write_robomimic(&h5);
    let store = Store::open(&StoreConfig::local(tmp.path().join("store"))).await.unwrap();
    let opts = IngestOptions {
        policy: "p".into(),
        checkpoint: "video".into(),
        images: ImageStorage::Video,
        ..Default::default()
    };
    let rep = ingest(&store, &h5, &opts).await.unwrap();
    assert_eq!((rep.episodes, rep.media_files), (DEMOS, DEMOS * CAMERAS.len()), "{rep:?}");

    let eps =
        store.episodes(&EpisodeFilter { version: Some(rep.version), ..Default::default() }).await.unwrap();
    assert_eq!(eps.len(), DEMOS);
    let mut worst = f64::INFINITY;
    let mut videos = Vec::new();
    for e in &eps {
        let d = demo_of(&e.source_name);
        let cams = store.episode_cameras(&e.id, None).await.unwrap();
        let listed: Vec<(&str, CameraKind)> = cams.iter().map(|c| (c.name.as_str(), c.kind)).collect();
        assert_eq!(
            listed,
            CAMERAS.iter().map(|c| (c.0, CameraKind::Video)).collect::<Vec<_>>(),
            "both cameras are videos, none left as PNG"
        );
        for (c, (name, h, w)) in CAMERAS.iter().enumerate() {
            let m = store.episode_media(&e.id, name).await.unwrap();
            assert_eq!(m.content_type.as_deref(), Some("video/mp4"), "{m:?}");
            let mp4 = store.get_object(&m.path).await.unwrap().to_vec();
            assert_eq!(Some(mp4.len() as u64), m.size_bytes);
            // Every frame, decoded from the stored object, against the frame the file holds.
            let mut times = Vec::new();
            let n = store::video::decode_all(mp4.clone(), |secs, f| {
                let t = times.len();
                assert_eq!((f.height, f.width), (*h, *w), "{name} frame {t}");
                let p = store::video::psnr(&frame(d, c, t, *h, *w), &f.rgb);
                assert!(p >= MIN_PSNR_DB, "{name} of demo {d}, frame {t}: PSNR {p:.1} dB < {MIN_PSNR_DB}");
                worst = worst.min(p);
                times.push(secs);
            })
            .unwrap();
            assert_eq!(n, STEPS, "{name}: one frame per step");
            // Robomimic steps are 1/control_freq apart: the video's frames too.
            for (t, s) in times.iter().enumerate() {
                assert!((s - t as f64 / 20.0).abs() < 1e-4, "{name} frame {t} at {s} s");
            }
            videos.push((mp4, d, c));
        }
        // The read path: one frame on request, decoded and served as PNG.
        for t in [0u64, 1, 31, STEPS as u64 - 1] {
            let png = store.read_frame(&e.id, None, CAMERAS[1].0, t).await.unwrap();
            let (w, h, rgb) = png_rgb(&png);
            assert_eq!((h, w), (CAMERAS[1].1, CAMERAS[1].2));
            let p = store::video::psnr(&frame(d, 1, t as usize, h, w), &rgb);
            assert!(p >= MIN_PSNR_DB, "read_frame step {t}: PSNR {p:.1} dB");
        }
        let past = store.read_frame(&e.id, None, CAMERAS[0].0, STEPS as u64).await.unwrap_err();
        assert!(matches!(past, store::StoreError::NotFound { .. }), "{past}");
    }
    println!("worst frame PSNR over {} videos: {worst:.1} dB", videos.len());

    pyav_decodes(tmp.path(), &videos);

    let rep = ingest(&store, &h5, &IngestOptions { checkpoint: "png".into(), ..opts.clone() }).await;
    assert!(rep.unwrap().already_ingested, "same content: already in the store");
}

/// The MP4s decoded with FFmpeg through PyAV (another decoder and demuxer than ours): as many
/// frames as steps, at the steps' times, within the PSNR bound.
fn pyav_decodes(dir: &Path, videos: &[(Vec<u8>, usize, usize)]) {
    if !store::test_support::require_python(&["av", "numpy"]) {
        return;
    }
    let code = r#"
import sys, av, numpy as np
mp4, raw, h, w, n = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
orig = np.fromfile(raw, np.uint8).reshape(n, h, w, 3).astype(np.float64)
with av.open(mp4) as c:
    s = c.streams.video[0]
    assert s.codec_context.name == "h264", s.codec_context.name
    frames = [(float(f.pts * s.time_base), f.to_ndarray(format="rgb24")) for f in c.decode(s)]
assert len(frames) == n, (len(frames), n)
worst = 99.0
for t, (secs, f) in enumerate(frames):
    assert abs(secs - t / 20) < 1e-4, (t, secs)
    mse = ((f.astype(np.float64) - orig[t]) ** 2).mean()
    worst = min(worst, 10 * np.log10(255 * 255 / mse) if mse > 0 else 99.0)
print(worst)
"#;
    for (i, (mp4, d, c)) in videos.iter().enumerate() {
        let (_, h, w) = CAMERAS[*c];
        let mp4_path = dir.join(format!("v{i}.mp4"));
        let raw_path = dir.join(format!("v{i}.rgb"));
        std::fs::write(&mp4_path, mp4).unwrap();
        let raw: Vec<u8> = (0..STEPS).flat_map(|t| frame(*d, *c, t, h, w)).collect();
        std::fs::write(&raw_path, raw).unwrap();
        let out = std::process::Command::new("python3")
            .args(["-c", code])
            .args([&mp4_path, &raw_path].map(|p| p.to_str().unwrap().to_string()))
            .args([h, w, STEPS].map(|x| x.to_string()))
            .output()
            .expect("run python3");
        assert!(out.status.success(), "PyAV on video {i}: {}", String::from_utf8_lossy(&out.stderr));
        let worst: f64 = String::from_utf8_lossy(&out.stdout).trim().parse().expect("a PSNR");
        // FFmpeg's YUV→RGB differs from OpenH264's by a rounding: a little slack.
        assert!(worst >= MIN_PSNR_DB - 1.0, "PyAV decodes video {i} at {worst:.1} dB");
    }
}

/// The encoder alone: frames pushed one at a time come back (OpenH264) within the bound, with
/// uneven step times kept; odd sizes are refused with a message, not a panic.
#[test]
fn encoder_round_trip_and_refusals() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("a.mp4");
    let mut enc = ingest::video::Mp4Encoder::create(&path, 96, 64).unwrap();
    let times = [0.0, 0.05, 0.11, 0.2, 0.2, 0.31];
    for (t, s) in times.iter().enumerate() {
        enc.push_frame(&frame(0, 1, t, 64, 96), *s).unwrap();
    }
    let v = enc.finish().unwrap();
    // Equal times are nudged one 90 kHz tick apart so every step keeps its own frame.
    assert!((v.timestamps[3] - 0.2).abs() < 1e-9 && v.timestamps[4] > v.timestamps[3], "{:?}", v.timestamps);
    let mp4 = std::fs::read(&path).unwrap();
    assert_eq!(v.size_bytes, mp4.len() as u64);
    for (t, s) in v.timestamps.iter().enumerate() {
        let f = store::video::decode_frame_at(mp4.clone(), *s).unwrap();
        let p = store::video::psnr(&frame(0, 1, t, 64, 96), &f.rgb);
        assert!(p >= MIN_PSNR_DB, "frame {t} at {s} s: {p:.1} dB");
    }
    let e = ingest::video::Mp4Encoder::create(&tmp.path().join("b.mp4"), 85, 64).err().expect("odd width");
    assert!(e.to_string().contains("85x64"), "{e}");
    // Not an MP4, or a truncated one: errors, not panics.
    assert!(store::video::decode_frame_at(b"not a video".to_vec(), 0.0).is_err());
    assert!(store::video::decode_frame_at(mp4[..mp4.len() / 2].to_vec(), 0.0).is_err());
}
