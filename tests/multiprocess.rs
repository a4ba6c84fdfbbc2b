//! Clusters of `cloudlight node` processes: one process per node on loopback, a node killed
//! and restarted, and (as root) two nodes in network namespaces joined by a veth pair.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

fn bin() -> PathBuf {
    assert_cmd::cargo::cargo_bin("cloudlight")
}

fn free_ports(n: usize) -> Vec<u16> {
    let sockets: Vec<_> = (0..n)
        .map(|_| std::net::UdpSocket::bind("127.0.0.1:0").unwrap())
        .collect();
    sockets
        .iter()
        .map(|s| s.local_addr().unwrap().port())
        .collect()
}

fn node(topology: &Path, name: &str, out: &Path, extra: &[&str]) -> Child {
    Command::new(bin())
        .args(["node"])
        .arg(topology)
        .args(["--node", name, "--connect-timeout", "20", "--out"])
        .arg(out.join(name))
        .args(extra)
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Waits for a child with a deadline, killing it if it overruns.
fn finish(mut child: Child, limit: Duration) -> Output {
    let start = Instant::now();
    while start.elapsed() < limit {
        if child.try_wait().unwrap().is_some() {
            return child.wait_with_output().unwrap();
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = child.kill();
    let out = child.wait_with_output().unwrap();
    panic!(
        "process overran {limit:?}; stderr:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn sink_report(out: &Path, node: &str, stage: &str) -> serde_json::Value {
    let m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join(node).join("metrics.json")).unwrap())
            .unwrap();
    m["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == stage)
        .unwrap()["report"]
        .clone()
}

/// Nodes `cloud` and `home` on free loopback ports, with `transport` settings and `body`
/// (stages and edges).
fn cloud_home(cluster: &str, transport: &str, body: &str) -> String {
    let ports = free_ports(2);
    format!(
        "techniques = [\"probe\"]\ncluster = \"{cluster}\"\nsecret = \"5d41402abc4b2a76\"\n\
         [transport]\n{transport}\n\
         [[node]]\nname = \"cloud\"\naddress = \"127.0.0.1:{}\"\n\
         [[node]]\nname = \"home\"\naddress = \"127.0.0.1:{}\"\n{body}",
        ports[0], ports[1]
    )
}

fn three_node_topology(ports: &[u16]) -> String {
    format!(
        r#"techniques = ["probe"]
cluster = "multiprocess-test"
secret = "shared"
duration_s = 3.0
[transport]
peer_timeout_ms = 3000
[[node]]
name = "a"
address = "127.0.0.1:{}"
[[node]]
name = "b"
address = "127.0.0.1:{}"
[[node]]
name = "c"
address = "127.0.0.1:{}"
[[stage]]
name = "source"
kind = "probe_source"
node = "a"
params = {{ rate_hz = 200.0, payload_bytes = 4000 }}
[[stage]]
name = "relay"
kind = "probe_relay"
node = "b"
[[stage]]
name = "sink"
kind = "probe_sink"
node = "c"
[[edge]]
from = "source"
to = "relay"
[[edge]]
from = "relay"
to = "sink"
[[link]]
between = ["a", "b"]
latency_ms = 2.0
loss = 0.01
"#,
        ports[0], ports[1], ports[2]
    )
}

#[test]
fn three_node_processes_run_a_pipeline_across_two_cuts_and_stop_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let topo = dir.path().join("three.toml");
    std::fs::write(&topo, three_node_topology(&free_ports(3))).unwrap();
    // Started in reverse order: each waits for the peers it needs.
    let children: Vec<(String, Child)> = ["c", "b", "a"]
        .iter()
        .map(|n| (n.to_string(), node(&topo, n, dir.path(), &[])))
        .collect();
    for (name, child) in children {
        let out = finish(child, Duration::from_secs(60));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "node {name} failed:\n{err}");
        assert!(err.contains("all peers up"), "node {name}:\n{err}");
    }
    let report = sink_report(dir.path(), "c", "sink");
    assert!(report["received"].as_u64().unwrap() > 100, "{report}");
    assert_eq!(report["corrupt"], 0);
    assert_eq!(report["out_of_order"], 0);
    let a: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("a/metrics.json")).unwrap()).unwrap();
    let edge = &a["edges"][0];
    assert_eq!(edge["wire"]["peer"], "b");
    assert!(
        edge["wire"]["retransmissions"].as_u64().unwrap() > 0,
        "1% loss causes retransmissions: {edge}"
    );
}

#[test]
fn a_killed_node_is_reported_lost_and_rejoins_when_restarted() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_ports(2);
    let topo = dir.path().join("two.toml");
    std::fs::write(
        &topo,
        format!(
            r#"techniques = ["probe"]
cluster = "restart-test"
secret = "test secret"
duration_s = 6.0
[transport]
peer_timeout_ms = 500
[[node]]
name = "a"
address = "127.0.0.1:{}"
[[node]]
name = "c"
address = "127.0.0.1:{}"
[[stage]]
name = "source"
kind = "probe_source"
node = "a"
params = {{ rate_hz = 100.0 }}
[[stage]]
name = "sink"
kind = "probe_sink"
node = "c"
[[edge]]
from = "source"
to = "sink"
"#,
            ports[0], ports[1]
        ),
    )
    .unwrap();
    let a = node(&topo, "a", dir.path(), &[]);
    let mut c = node(&topo, "c", dir.path(), &["--duration", "60"]);
    std::thread::sleep(Duration::from_millis(1500));
    c.kill().unwrap();
    c.wait().unwrap();
    std::thread::sleep(Duration::from_millis(1200));
    let c2 = node(&topo, "c", &dir.path().join("again"), &["--duration", "2"]);
    let out_c2 = finish(c2, Duration::from_secs(30));
    assert!(
        out_c2.status.success(),
        "{}",
        String::from_utf8_lossy(&out_c2.stderr)
    );
    let out_a = finish(a, Duration::from_secs(30));
    let err = String::from_utf8_lossy(&out_a.stderr);
    assert!(out_a.status.success(), "{err}");
    let lost = err.find("peer lost").expect("a reports c lost");
    let restarted = err
        .find("peer restarted")
        .expect("a sees c's new incarnation");
    assert!(lost < restarted, "{err}");
    let report = sink_report(&dir.path().join("again"), "c", "sink");
    assert!(
        report["received"].as_u64().unwrap() > 20,
        "the restarted node receives again: {report}"
    );
}

#[test]
fn a_receiver_whose_upstream_crashes_for_good_fails_and_names_it() {
    let dir = tempfile::tempdir().unwrap();
    let topo = dir.path().join("crash.toml");
    let text = cloud_home(
        "crash-test",
        "peer_timeout_ms = 500\nrejoin_timeout_s = 1.5",
        r#"
[[stage]]
name = "source"
kind = "probe_source"
node = "cloud"
params = { rate_hz = 100.0 }
[[stage]]
name = "sink"
kind = "probe_sink"
node = "home"
[[edge]]
from = "source"
to = "sink"
"#,
    );
    std::fs::write(&topo, text).unwrap();
    let mut cloud = node(&topo, "cloud", dir.path(), &["--duration", "60"]);
    let home = node(&topo, "home", dir.path(), &["--duration", "60"]);
    std::thread::sleep(Duration::from_millis(1500));
    cloud.kill().unwrap();
    cloud.wait().unwrap();
    let killed = Instant::now();
    let out = finish(home, Duration::from_secs(30));
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(5), "{err}");
    assert!(
        err.contains("peer `cloud` was lost and has not come back"),
        "{err}"
    );
    assert!(
        killed.elapsed() < Duration::from_secs(10),
        "failed {:?} after the crash",
        killed.elapsed()
    );
    let m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("home/metrics.json")).unwrap())
            .unwrap();
    assert_eq!(m["status"], "failed");
    assert_eq!(m["transport"][0]["peers"][0]["state"], "lost", "{m}");
}

#[test]
fn a_relay_killed_and_restarted_loses_nothing_that_is_not_counted() {
    // a -> b -> c; b is killed with SIGKILL mid-run and started again. Every message the
    // source sent is received, or counted missing at the sink (whether it was lost in a's
    // transport, inside b, or on its way to c), or was sent after the sink's last one.
    let dir = tempfile::tempdir().unwrap();
    let ports = free_ports(3);
    let text = three_node_topology(&ports)
        .replace("duration_s = 3.0\n", "")
        .replace(
            "peer_timeout_ms = 3000",
            "peer_timeout_ms = 500\nrejoin_timeout_s = 20",
        );
    let topo = dir.path().join("chain.toml");
    std::fs::write(&topo, &text).unwrap();
    let c = node(&topo, "c", dir.path(), &[]);
    let mut b = node(&topo, "b", dir.path(), &[]);
    let a = node(&topo, "a", dir.path(), &["--duration", "5"]);
    std::thread::sleep(Duration::from_millis(2000));
    b.kill().unwrap();
    b.wait().unwrap();
    std::thread::sleep(Duration::from_millis(700));
    let b2 = node(&topo, "b", &dir.path().join("again"), &[]);
    for (name, child) in [("a", a), ("b", b2), ("c", c)] {
        let out = finish(child, Duration::from_secs(60));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "node {name}:\n{err}");
    }
    let source = sink_report(dir.path(), "a", "source");
    let sink = sink_report(dir.path(), "c", "sink");
    let sent = source["sent"].as_u64().unwrap();
    let received = sink["received"].as_u64().unwrap();
    let missing = sink["missing"].as_u64().unwrap();
    let last = sink["last_index"].as_u64().unwrap();
    assert_eq!(sink["corrupt"], 0);
    assert!(received > 100, "{sink}");
    assert_eq!(
        received + missing + (sent - last - 1),
        sent,
        "source {source}\nsink {sink}"
    );
    // a gave up on what the old b had not confirmed consuming: the sink's count is the
    // truth (b may have forwarded some of them just before it died).
    let a: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("a/metrics.json")).unwrap()).unwrap();
    let gave_up = a["edges"][0]["wire"]["lost"].as_u64().unwrap();
    assert!(gave_up > 0, "b held messages when it was killed: {a}");
}

#[test]
fn a_receiver_whose_upstream_fails_with_an_error_fails_too() {
    // The relay on `cloud` fails after 5 messages: cloud exits 3 and says so in its goodbye;
    // `home`, whose input ended early, must not report success (as it does for a crash).
    let dir = tempfile::tempdir().unwrap();
    let topo = dir.path().join("fail.toml");
    let text = cloud_home(
        "upstream-failure-test",
        "",
        r#"
[[stage]]
name = "source"
kind = "probe_source"
node = "cloud"
params = { rate_hz = 50.0 }
[[stage]]
name = "relay"
kind = "probe_relay"
node = "cloud"
params = { fail_after = 5 }
[[stage]]
name = "sink"
kind = "probe_sink"
node = "home"
[[edge]]
from = "source"
to = "relay"
[[edge]]
from = "relay"
to = "sink"
"#,
    );
    std::fs::write(&topo, text).unwrap();
    let home = node(&topo, "home", dir.path(), &["--duration", "60"]);
    let cloud = node(&topo, "cloud", dir.path(), &["--duration", "60"]);
    let out = finish(cloud, Duration::from_secs(60));
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{err}");
    let out = finish(home, Duration::from_secs(30));
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(5), "{err}");
    assert!(
        err.contains("upstream peer `cloud` stopped because its run failed"),
        "{err}"
    );
    let m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("home/metrics.json")).unwrap())
            .unwrap();
    assert_eq!(m["status"], "failed", "{m}");
}

#[test]
fn a_photon_client_that_rejoins_gets_the_current_set() {
    // The static Cornell box: the batcher traces its one batch once and never again. A client
    // node killed and restarted still gets the current set, from the batcher's re-send.
    let dir = tempfile::tempdir().unwrap();
    let ports = free_ports(2);
    let topo = dir.path().join("photons.toml");
    std::fs::write(
        &topo,
        format!(
            r#"techniques = ["photons"]
scene = "cornell"
cluster = "photon-rejoin"
secret = "test secret"
duration_s = 7.0
[transport]
peer_timeout_ms = 500
[[node]]
name = "cloud"
address = "127.0.0.1:{}"
[[node]]
name = "home"
address = "127.0.0.1:{}"
[[stage]]
name = "batcher"
kind = "photon_batcher"
node = "cloud"
params = {{ photons = 5000, batch_size = 5000, interval_ms = 50.0, resend_s = 0.5 }}
[[stage]]
name = "client"
kind = "photon_reconstructor"
node = "home"
params = {{ render = false }}
[[edge]]
from = "batcher"
to = "client"
"#,
            ports[0], ports[1]
        ),
    )
    .unwrap();
    let cloud = node(&topo, "cloud", dir.path(), &[]);
    let mut home = node(&topo, "home", dir.path(), &["--duration", "60"]);
    std::thread::sleep(Duration::from_millis(1500));
    home.kill().unwrap();
    home.wait().unwrap();
    std::thread::sleep(Duration::from_millis(1000));
    let again = node(
        &topo,
        "home",
        &dir.path().join("again"),
        &["--duration", "2.5"],
    );
    let out = finish(again, Duration::from_secs(30));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out_cloud = finish(cloud, Duration::from_secs(30));
    assert!(
        out_cloud.status.success(),
        "{}",
        String::from_utf8_lossy(&out_cloud.stderr)
    );
    let client = sink_report(&dir.path().join("again"), "home", "client");
    assert_eq!(client["indirect_shown"], true, "{client}");
    assert!(
        client["photons_stored"].as_u64().unwrap() > 1000,
        "{client}"
    );
    let batcher = sink_report(dir.path(), "cloud", "batcher");
    assert_eq!(
        batcher["batches_traced"], 1,
        "a static light is traced once: {batcher}"
    );
    assert!(batcher["resends"].as_u64().unwrap() >= 4, "{batcher}");
}

/// Network namespaces, one per node, joined by a bridge in a namespace of their own (a hub),
/// node `i` at `10.213.7.(i+1)/24`; removed on drop, with any `/etc/netns/NAME/` files
/// (which `ip netns exec` mounts over `/etc`: a node's own `/etc/hosts`).
struct Namespaces {
    hub: String,
    names: Vec<String>,
}

fn ip(args: &[&str]) -> bool {
    let ok = Command::new("ip")
        .args(args)
        .status()
        .map(|st| st.success())
        .unwrap_or(false);
    if !ok {
        eprintln!("`ip {}` failed", args.join(" "));
    }
    ok
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .map(|o| o.stdout == b"0\n")
        .unwrap_or(false)
}

impl Namespaces {
    fn create(n: usize) -> Option<Namespaces> {
        // Unique per process and per set (tests run in parallel threads of one process).
        static SETS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let k = SETS.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        let id = std::process::id() % 100_000;
        let ns = Namespaces {
            hub: format!("cl-hub-{id}-{k}"),
            names: (0..n).map(|i| format!("cl-{id}-{k}-{i}")).collect(),
        };
        let hub = ns.hub.as_str();
        // Drop removes whatever was made if a step fails.
        if !(ip(&["netns", "add", hub])
            && ip(&["-n", hub, "link", "add", "br0", "type", "bridge"])
            && ip(&["-n", hub, "link", "set", "br0", "up"]))
        {
            return None;
        }
        for (i, name) in ns.names.iter().enumerate() {
            let (inner, outer) = (format!("cl{id}x{k}n{i}"), format!("ch{id}x{k}n{i}"));
            let addr = format!("10.213.7.{}/24", i + 1);
            let ok = ip(&["netns", "add", name])
                && ip(&[
                    "link", "add", &inner, "type", "veth", "peer", "name", &outer,
                ])
                && ip(&["link", "set", &inner, "netns", name])
                && ip(&["link", "set", &outer, "netns", hub])
                && ip(&["-n", hub, "link", "set", &outer, "master", "br0"])
                && ip(&["-n", hub, "link", "set", &outer, "up"])
                && ip(&["-n", name, "addr", "add", &addr, "dev", &inner])
                && ip(&["-n", name, "link", "set", &inner, "up"])
                && ip(&["-n", name, "link", "set", "lo", "up"]);
            if !ok {
                return None;
            }
        }
        Some(ns)
    }

    /// Node `i`'s address.
    fn ip(i: usize) -> String {
        format!("10.213.7.{}", i + 1)
    }

    /// Gives every namespace an `/etc/hosts` naming these hosts.
    fn hosts(&self, entries: &[(String, String)]) {
        let mut text = String::from("127.0.0.1 localhost\n");
        for (host, ip) in entries {
            text.push_str(&format!("{ip} {host}\n"));
        }
        for n in &self.names {
            let dir = Path::new("/etc/netns").join(n);
            std::fs::create_dir_all(&dir).unwrap();
            std::fs::write(dir.join("hosts"), &text).unwrap();
        }
    }
}

impl Drop for Namespaces {
    fn drop(&mut self) {
        for n in self.names.iter().chain([&self.hub]) {
            let _ = Command::new("ip").args(["netns", "del", n]).status();
            let _ = std::fs::remove_dir_all(Path::new("/etc/netns").join(n));
        }
    }
}

#[test]
fn two_nodes_in_network_namespaces_joined_by_a_bridge() {
    if !is_root() {
        eprintln!("skipped: creating network namespaces needs root (CI runs as root)");
        return;
    }
    let ns = Namespaces::create(2).expect("root can create network namespaces and a bridge");
    let dir = tempfile::tempdir().unwrap();
    let topo = dir.path().join("netns.toml");
    std::fs::write(
        &topo,
        r#"techniques = ["probe"]
cluster = "netns-test"
secret = "test secret"
duration_s = 2.0
[[node]]
name = "a"
address = "10.213.7.1:7400"
[[node]]
name = "b"
address = "10.213.7.2:7400"
[[stage]]
name = "source"
kind = "probe_source"
node = "a"
params = { rate_hz = 100.0, payload_bytes = 20000 }
[[stage]]
name = "sink"
kind = "probe_sink"
node = "b"
[[edge]]
from = "source"
to = "sink"
"#,
    )
    .unwrap();
    let spawn = |netns: &str, name: &str| {
        Command::new("ip")
            .args(["netns", "exec", netns])
            .arg(bin())
            .args(["node"])
            .arg(&topo)
            .args(["--node", name, "--connect-timeout", "20", "--out"])
            .arg(dir.path().join(name))
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let b = spawn(&ns.names[1], "b");
    let a = spawn(&ns.names[0], "a");
    for (name, child) in [("a", a), ("b", b)] {
        let out = finish(child, Duration::from_secs(60));
        assert!(
            out.status.success(),
            "node {name}:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let report = sink_report(dir.path(), "b", "sink");
    assert!(report["received"].as_u64().unwrap() > 50, "{report}");
    assert_eq!(report["corrupt"], 0);
    drop(ns);
}

#[test]
fn nodes_listen_on_their_bind_address_with_the_secret_from_the_environment() {
    // Each node listens on every interface (`bind` in the file for `c`, `--bind` for `b`)
    // while its peers dial its loopback `address`; the secret is in no file.
    let dir = tempfile::tempdir().unwrap();
    let ports = free_ports(3);
    let text = three_node_topology(&ports)
        .replace(
            "secret = \"shared\"",
            "secret_env = \"CLOUDLIGHT_TEST_SECRET\"",
        )
        .replace(
            &format!("address = \"127.0.0.1:{}\"", ports[2]),
            &format!(
                "address = \"127.0.0.1:{}\"\nbind = \"0.0.0.0:{}\"",
                ports[2], ports[2]
            ),
        );
    let topo = dir.path().join("three.toml");
    std::fs::write(&topo, &text).unwrap();
    let bind_b = format!("0.0.0.0:{}", ports[1]);
    let children: Vec<(String, Child)> = ["c", "b", "a"]
        .iter()
        .map(|n| {
            let extra: Vec<&str> = if *n == "b" {
                vec!["--bind", &bind_b]
            } else {
                vec![]
            };
            let mut cmd = Command::new(bin());
            cmd.args(["node"])
                .arg(&topo)
                .args(["--node", n, "--connect-timeout", "20", "--out"])
                .arg(dir.path().join(n))
                .args(&extra)
                .env("RUST_LOG", "info")
                .env("CLOUDLIGHT_TEST_SECRET", "from-the-environment")
                .stdout(Stdio::piped())
                .stderr(Stdio::piped());
            (n.to_string(), cmd.spawn().unwrap())
        })
        .collect();
    for (name, child) in children {
        let out = finish(child, Duration::from_secs(60));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "node {name} failed:\n{err}");
        if name != "a" {
            assert!(
                err.contains(&format!(
                    "0.0.0.0:{}",
                    ports[if name == "b" { 1 } else { 2 }]
                )),
                "node {name} listens on every interface:\n{err}"
            );
        }
        assert!(
            !err.contains("from-the-environment"),
            "the secret is printed:\n{err}"
        );
    }
    let report = sink_report(dir.path(), "c", "sink");
    assert!(report["received"].as_u64().unwrap() > 100, "{report}");
    assert_eq!(report["corrupt"], 0);

    // Without the variable: exit 2 naming the file, line and key, before anything starts.
    let out = Command::new(bin())
        .args(["node"])
        .arg(&topo)
        .args(["--node", "a"])
        .env_remove("CLOUDLIGHT_TEST_SECRET")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("three.toml:3:")
            && err.contains("`secret_env`")
            && err.contains("CLOUDLIGHT_TEST_SECRET")
            && err.contains("not set"),
        "{err}"
    );
    // A bind address another socket holds: a clear error, non-zero, before any stage runs.
    let held = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let taken = held.local_addr().unwrap().to_string();
    let out = Command::new(bin())
        .args(["node"])
        .arg(&topo)
        .args(["--node", "a", "--bind", &taken, "--out"])
        .arg(dir.path().join("clash"))
        .env("CLOUDLIGHT_TEST_SECRET", "from-the-environment")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(err.contains(&taken) && err.contains("in use"), "{err}");
    assert!(!err.contains("cluster started"), "{err}");
}

/// `GET path` from `addr`: (status, body); `None` when nothing answers.
fn http_get(addr: &str, path: &str) -> Option<(u16, String)> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut text = String::new();
    s.read_to_string(&mut text).ok()?;
    let (head, body) = text.split_once("\r\n\r\n")?;
    let status = head.split_whitespace().nth(1)?.parse().ok()?;
    Some((status, body.to_string()))
}

fn free_tcp_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

#[test]
fn metrics_and_health_are_served_over_http_and_health_turns_503_when_a_peer_dies() {
    let dir = tempfile::tempdir().unwrap();
    let topo = dir.path().join("three.toml");
    std::fs::write(&topo, three_node_topology(&free_ports(3))).unwrap();
    let listen = format!("127.0.0.1:{}", free_tcp_port());
    let c = node(
        &topo,
        "c",
        dir.path(),
        &[
            "--duration",
            "30",
            "--metrics-listen",
            &listen,
            "--metrics-interval",
            "0.5",
        ],
    );
    let b = node(&topo, "b", dir.path(), &["--duration", "30"]);
    let a = node(&topo, "a", dir.path(), &["--duration", "30"]);
    let until = |what: &str, limit: Duration, ok: &dyn Fn() -> bool| {
        let start = Instant::now();
        while !ok() {
            assert!(start.elapsed() < limit, "{what} not within {limit:?}");
            std::thread::sleep(Duration::from_millis(100));
        }
    };
    // Healthy once its peer is up and the run is running.
    until("/healthz 200", Duration::from_secs(30), &|| {
        http_get(&listen, "/healthz").is_some_and(|(code, _)| code == 200)
    });
    // /metrics parses as Prometheus text and agrees with metrics.json at the same moment
    // (the same snapshot: same elapsed time).
    let json_path = dir.path().join("c").join("metrics.json");
    let mut agreed = false;
    for _ in 0..100 {
        let (code, text) = http_get(&listen, "/metrics").unwrap();
        assert_eq!(code, 200);
        let json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&json_path).unwrap()).unwrap();
        let scrape = prometheus_parse::Scrape::parse(text.lines().map(|l| Ok(l.to_string())))
            .unwrap_or_else(|e| panic!("{e}:\n{text}"));
        let value = |name: &str, stage: Option<&str>| {
            scrape
                .samples
                .iter()
                .find(|s| {
                    s.metric == name && stage.is_none_or(|st| s.labels.get("stage") == Some(st))
                })
                .map(|s| match s.value {
                    prometheus_parse::Value::Counter(v)
                    | prometheus_parse::Value::Gauge(v)
                    | prometheus_parse::Value::Untyped(v) => v,
                    _ => f64::NAN,
                })
                .unwrap_or_else(|| panic!("no {name} in:\n{text}"))
        };
        if value("cloudlight_run_elapsed_seconds", None) != json["elapsed_s"].as_f64().unwrap() {
            continue; // a snapshot was taken between the two reads
        }
        let sink = json["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == "sink")
            .unwrap();
        assert_eq!(
            value("cloudlight_stage_handled_total", Some("sink")),
            sink["handled"].as_f64().unwrap(),
            "{text}"
        );
        if sink["handled"].as_u64().unwrap() == 0 {
            std::thread::sleep(Duration::from_millis(200));
            continue; // nothing has arrived yet
        }
        assert_eq!(value("cloudlight_run_up", None), 1.0);
        agreed = true;
        break;
    }
    assert!(agreed, "/metrics never matched metrics.json");
    // The relay is killed: c's health turns 503 and names it.
    let mut b = b;
    b.kill().unwrap();
    let _ = b.wait();
    until("/healthz 503 naming b", Duration::from_secs(20), &|| {
        http_get(&listen, "/healthz")
            .is_some_and(|(code, body)| code == 503 && body.contains("peer `b`"))
    });
    for mut child in [a, c] {
        let _ = child.kill();
        let _ = child.wait();
    }

    // A metrics address another socket holds: a clear error, non-zero, before any stage.
    let held = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let taken = held.local_addr().unwrap().to_string();
    let out = Command::new(bin())
        .args(["node"])
        .arg(&topo)
        .args(["--node", "a", "--metrics-listen", &taken, "--out"])
        .arg(dir.path().join("clash"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("cannot serve /metrics") && err.contains(&taken),
        "{err}"
    );
    assert!(!err.contains("cluster started"), "{err}");
}

#[test]
fn nodes_of_different_topologies_refuse_each_other_and_exit_5() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_ports(3);
    let mine = dir.path().join("mine.toml");
    let theirs = dir.path().join("theirs.toml");
    let text = three_node_topology(&ports);
    std::fs::write(&mine, &text).unwrap();
    std::fs::write(&theirs, text.replace("rate_hz = 200.0", "rate_hz = 100.0")).unwrap();
    let a = node(&mine, "a", dir.path(), &[]);
    let b = node(&theirs, "b", dir.path(), &[]);
    for (name, child) in [("a", a), ("b", b)] {
        let out = finish(child, Duration::from_secs(60));
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(5), "node {name}:\n{err}");
        assert!(err.contains("different topology"), "node {name}:\n{err}");
    }
}

/// A three-node chain with a fixed number of messages on `block` edges: every run of it, in
/// one process or many, delivers all of them to both clients.
const DEPLOYED: &str = r#"techniques = ["probe"]
cluster = "manifest-test"
[[node]]
name = "cloud"
address = "127.0.0.1:0"
[[node]]
name = "edge"
address = "127.0.0.1:0"
[[node]]
name = "home"
address = "127.0.0.1:0"
[[stage]]
name = "source"
kind = "probe_source"
node = "cloud"
params = { rate_hz = 400.0, payload_bytes = 3000, count = 400 }
[[stage]]
name = "relay"
kind = "probe_relay"
node = "edge"
[[stage]]
name = "client"
kind = "probe_sink"
node = "home"
replicas = 2
[[edge]]
from = "source"
to = "relay"
[[edge]]
from = "relay"
to = "client"
[[link]]
between = ["cloud", "edge"]
latency_ms = 2.0
loss = 0.02
"#;

#[test]
fn the_commands_of_the_kubernetes_manifests_run_a_cluster_in_network_namespaces() {
    // Each node runs the command and environment its StatefulSet gives its pod, in its own
    // network namespace, with the peers at their pods' DNS names (an /etc/hosts per
    // namespace stands in for the cluster's DNS), binding 0.0.0.0 while advertised by name,
    // and the secret only in the environment. It delivers what one process delivers.
    if !is_root() {
        eprintln!("skipped: creating network namespaces needs root (CI runs as root)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("deployed.toml");
    std::fs::write(&file, DEPLOYED).unwrap();
    let registry = cloudlight::actors::registry();
    let plan = cloudlight::runtime::Plan::load(&file, &registry).unwrap();

    // In one process.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let options = cloudlight::runtime::RunOptions {
        out_dir: Some(dir.path().join("one-process")),
        ..Default::default()
    };
    let report = rt
        .block_on(cloudlight::runtime::run(
            &plan,
            &registry,
            options,
            std::future::pending(),
        ))
        .unwrap_or_else(|e| panic!("{e}"));
    let in_process: Vec<serde_json::Value> = ["client[0]", "client[1]"]
        .iter()
        .map(|c| {
            report
                .metrics
                .stages
                .iter()
                .find(|s| s.name == *c)
                .unwrap()
                .report
                .clone()
                .unwrap()
        })
        .collect();
    for r in &in_process {
        assert_eq!(r["received"], 400, "{r}");
    }

    // From the manifests.
    let manifests = dir.path().join("manifests");
    let options = cloudlight::deploy::Options {
        image: "cloudlight:test".into(),
        namespace: "lights".into(),
    };
    let d = cloudlight::deploy::kubernetes(&plan, &file, &options, &manifests).unwrap();
    let objects: Vec<serde_json::Value> = d
        .files
        .iter()
        .map(|f| serde_json::from_slice(&std::fs::read(f).unwrap()).unwrap())
        .collect();
    let kind = |k: &'static str| objects.iter().filter(move |o| o["kind"] == k);
    let config = kind("ConfigMap").next().unwrap();
    let secret = kind("Secret").next().unwrap()["stringData"]["secret"]
        .as_str()
        .unwrap()
        .to_string();
    let etc = dir.path().join("etc-cloudlight");
    std::fs::create_dir_all(&etc).unwrap();
    std::fs::write(
        etc.join("topology.toml"),
        config["data"]["topology.toml"].as_str().unwrap(),
    )
    .unwrap();
    let ns = Namespaces::create(d.nodes.len()).expect("root can create network namespaces");
    let hosts: Vec<(String, String)> = d
        .nodes
        .iter()
        .enumerate()
        .map(|(i, n)| {
            let host = n.address.rsplit_once(':').unwrap().0.to_string();
            (host, Namespaces::ip(i))
        })
        .collect();
    ns.hosts(&hosts);
    // Started downstream first, as a StatefulSet might; each waits for its peers.
    let mut children = Vec::new();
    for (i, n) in d.nodes.iter().enumerate().rev() {
        let set = kind("StatefulSet")
            .find(|s| s["spec"]["serviceName"] == n.name)
            .unwrap();
        let c = &set["spec"]["template"]["spec"]["containers"][0];
        let mount = c["volumeMounts"][0]["mountPath"].as_str().unwrap();
        let mut args: Vec<String> = c["args"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| a.as_str().unwrap().replace(mount, etc.to_str().unwrap()))
            .collect();
        let out = args.iter().position(|a| a == "--out").unwrap() + 1;
        args[out] = dir.path().join(&n.node).display().to_string();
        let env = &c["env"][0];
        assert_eq!(
            env["valueFrom"]["secretKeyRef"]["name"],
            kind("Secret").next().unwrap()["metadata"]["name"]
        );
        let child = Command::new("ip")
            .args(["netns", "exec", &ns.names[i]])
            .arg(bin())
            .args(&args)
            .env(env["name"].as_str().unwrap(), &secret)
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        children.push((n.node.clone(), child));
    }
    for (name, child) in children {
        let out = finish(child, Duration::from_secs(90));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "node {name}:\n{err}");
        assert!(!err.contains(&secret), "node {name} printed the secret");
        if name == "home" {
            assert!(err.contains("0.0.0.0:"), "binds every interface:\n{err}");
        }
    }
    for (i, expected) in in_process.iter().enumerate() {
        let got = sink_report(dir.path(), "home", &format!("client[{i}]"));
        for key in ["received", "bytes", "missing", "out_of_order", "corrupt"] {
            assert_eq!(got[key], expected[key], "client[{i}] {key}: {got}");
        }
    }
    drop(ns);
}
