//! `vlem run --serve` end to end: the demo run serves its live map on a loopback port, a plain
//! HTTP client (ureq, not vlem's own client) exercises every endpoint and its error answers, and
//! `vlem query --connect` prints what `vlem query --map` prints for the saved map.
#![cfg(feature = "cli")]
#![cfg(all(feature = "colour-names", feature = "point-cloud"))]
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]

mod common;

use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use common::{ok, repo, spawn_serving};

/// A `vlem run --serve 127.0.0.1:0 --serve-after` child, killed on drop.
struct Served {
    child: Child,
    address: String,
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts the demo config with a server and returns once the server's address is printed.
fn serve(out: &Path, extra: &[&str]) -> Served {
    let mut args = vec!["run", "--config", "configs/demo.toml", "--out"];
    let out = out.to_str().unwrap();
    args.push(out);
    args.extend(["--serve", "127.0.0.1:0", "--serve-after"]);
    args.extend(extra);
    let (child, address) = spawn_serving(&args);
    Served { child, address }
}

fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(60)))
        .build()
        .new_agent()
}

fn get(address: &str, path: &str) -> (u16, Vec<u8>) {
    let mut response = agent()
        .get(format!("http://{address}{path}"))
        .call()
        .unwrap();
    let status = response.status().as_u16();
    let body = response
        .body_mut()
        .with_config()
        .limit(u64::MAX)
        .read_to_vec()
        .unwrap();
    (status, body)
}

fn post(address: &str, path: &str, body: &str) -> (u16, serde_json::Value) {
    let mut response = agent()
        .post(format!("http://{address}{path}"))
        .header("Content-Type", "application/json")
        .send(body)
        .unwrap();
    let status = response.status().as_u16();
    let text = response.body_mut().read_to_string().unwrap();
    let value = serde_json::from_str(&text).unwrap_or_else(|_| panic!("JSON answer: {text}"));
    (status, value)
}

fn json(body: &[u8]) -> serde_json::Value {
    serde_json::from_slice(body).unwrap()
}

/// Polls `/status` until the run has finished.
fn wait_finished(address: &str) -> serde_json::Value {
    let start = Instant::now();
    loop {
        let (status, body) = get(address, "/status");
        assert_eq!(status, 200);
        let value = json(&body);
        if value["run"]["state"] == "finished" {
            return value;
        }
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "the run finishes: {value}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn every_endpoint_answers_and_bad_requests_get_4xx() {
    let dir = tempfile::tempdir().unwrap();
    let served = serve(dir.path(), &[]);
    let address = served.address.clone();

    // Status answers while mapping and after.
    let (status, body) = get(&address, "/status");
    assert_eq!(status, 200);
    let first = json(&body);
    assert_eq!(first["encoder"], "colour-names");
    let done = wait_finished(&address);
    // `finished` comes only once the outputs are written (`saving` before).
    for output in ["map.vlem", "trajectory.tum", "stats.json"] {
        assert!(dir.path().join(output).is_file(), "{output} is written");
    }
    assert!(
        first["run"]["frames_integrated"].as_u64() <= done["run"]["frames_integrated"].as_u64()
    );
    assert_eq!(done["run"]["frames_total"], 30);
    assert_eq!(done["run"]["frames_integrated"], 30);
    assert_eq!(done["map"]["kind"], "point-cloud");
    assert_eq!(done["map"]["frames_integrated"], 30);
    let points = done["map"]["points"].as_u64().unwrap();
    assert!(points > 1000);
    let pose = &done["run"]["latest_pose"];
    assert_eq!(pose["index"], 29);
    assert_eq!(pose["pose"]["orientation"].as_array().unwrap().len(), 4);

    // Queries, with point sets and a grasp.
    let (status, answer) = post(
        &address,
        "/query",
        r#"{"texts": ["white wall", "brown"], "segmenter": "cluster", "baseline": "grey", "grasp": true, "indices": true}"#,
    );
    assert_eq!(status, 200, "{answer}");
    assert_eq!(answer["segmenter"], "cluster");
    assert_eq!(answer["points"].as_u64(), Some(points));
    let queries = answer["queries"].as_array().unwrap();
    assert_eq!(queries.len(), 2);
    assert_eq!(queries[0]["text"], "white wall");
    assert!(queries[0]["best"]["score"].as_f64().unwrap() > 0.5);
    let sets = queries[0]["sets"].as_array().unwrap();
    assert!(!sets.is_empty());
    assert_eq!(
        sets[0]["indices"].as_array().unwrap().len() as u64,
        sets[0]["points"].as_u64().unwrap()
    );
    assert!(queries[0]["grasp"]["outcome"].is_string());

    // The heatmap is a binary PLY with one vertex per map point.
    let (status, ply) = get(&address, "/heatmap.ply?text=white+wall");
    assert_eq!(status, 200);
    let header = String::from_utf8_lossy(&ply[..300.min(ply.len())]).into_owned();
    assert!(
        header.starts_with("ply\nformat binary_little_endian 1.0"),
        "{header}"
    );
    assert!(
        header.contains(&format!("element vertex {points}\n")),
        "{header}"
    );

    // Snapshots: saved on the server's side under names it chooses, and downloaded.
    let (status, saved) = post(&address, "/snapshot", "");
    assert_eq!(status, 200, "{saved}");
    assert_eq!(saved["file"], "snapshot-0001.vlem");
    assert_eq!(saved["points"].as_u64(), Some(points));
    let (status, second) = post(&address, "/snapshot", "{}");
    assert_eq!(status, 200, "{second}");
    assert_eq!(second["file"], "snapshot-0002.vlem");
    let snap = vlem_core::read_map_file(&dir.path().join("snapshot-0001.vlem")).unwrap();
    assert_eq!(snap.len() as u64, points);
    let (status, file) = get(&address, "/map.vlem");
    assert_eq!(status, 200);
    let downloaded = vlem_core::mapfile::map_file_from_bytes(&file, Path::new("map.vlem")).unwrap();
    assert_eq!(downloaded, snap);

    // Bad requests: a message and a 4xx, and the server keeps serving.
    let cases: [(&str, &str, u16, &str); 5] = [
        ("/query", "not json", 400, "bad query request"),
        (
            "/query",
            r#"{"texts": ["red"], "colour": 1}"#,
            400,
            "unknown field",
        ),
        ("/query", r#"{"texts": []}"#, 400, "no query texts"),
        (
            "/query",
            r#"{"texts": ["red"], "segmenter": "nope"}"#,
            400,
            "nope",
        ),
        (
            "/query",
            r#"{"texts": ["coffee machine"]}"#,
            422,
            "cannot embed the query",
        ),
    ];
    for (path, body, code, message) in cases {
        let (status, reply) = post(&address, path, body);
        assert_eq!(status, code, "{body}: {reply}");
        let error = reply["error"].as_str().unwrap();
        assert!(error.contains(message), "{body}: {error}");
    }
    let (status, body) = get(&address, "/nowhere");
    assert_eq!(status, 404);
    assert!(
        json(&body)["error"]
            .as_str()
            .unwrap()
            .contains("POST /query")
    );
    let (status, _) = get(&address, "/query");
    assert_eq!(status, 405);
    let (status, body) = get(&address, "/heatmap.ply");
    assert_eq!(status, 400);
    assert!(
        json(&body)["error"]
            .as_str()
            .unwrap()
            .contains("exactly one text")
    );
    let (status, _) = get(&address, "/status");
    assert_eq!(status, 200, "still serving after the bad requests");
}

/// One request written by hand on a fresh connection (so that Host, Origin and the rest are
/// exactly what a hostile page or program would send): the status and the body.
fn raw(address: &str, head: &str, body: &str) -> (u16, String) {
    use std::io::{Read, Write};
    let mut stream = std::net::TcpStream::connect(address).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    let request = format!(
        "{head}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(request.as_bytes()).unwrap();
    let mut answer = String::new();
    stream.read_to_string(&mut answer).unwrap();
    let (status, body) = status_and_body(&answer);
    (status, body.to_owned())
}

/// An HTTP answer's status and body.
fn status_and_body(answer: &str) -> (u16, &str) {
    let status = answer
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("an HTTP answer: {answer}"));
    (status, answer.split_once("\r\n\r\n").map_or("", |(_, b)| b))
}

#[test]
fn hostile_requests_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let served = serve(&out, &[]);
    let address = served.address.clone();
    let port = address.rsplit(':').next().unwrap();
    let host = format!("Host: 127.0.0.1:{port}");

    // A request path names no file: snapshots go into the output folder under the server's names.
    let victim = dir.path().join("victim");
    std::fs::write(&victim, "keep me").unwrap();
    for body in [
        format!(r#"{{"path": "{}"}}"#, victim.display()),
        r#"{"path": "../victim"}"#.to_owned(),
    ] {
        let (status, reply) = post(&address, "/snapshot", &body);
        assert_eq!(status, 400, "{body}: {reply}");
        assert!(
            reply["error"]
                .as_str()
                .unwrap()
                .contains("takes no options"),
            "{reply}"
        );
    }
    assert_eq!(std::fs::read_to_string(&victim).unwrap(), "keep me");
    assert!(!out.join("snapshot-0001.vlem").exists());

    // DNS rebinding: a page's own host name in Host.
    for forged in ["Host: attacker.example", "Host: attacker.example:80"] {
        let (status, body) = raw(&address, &format!("GET /map.vlem HTTP/1.1\r\n{forged}"), "");
        assert_eq!(status, 403, "{forged}: {body}");
        assert!(body.contains("not this server"), "{body}");
    }
    let (status, _) = raw(&address, "GET /status HTTP/1.1", "");
    assert_eq!(status, 400, "a request without Host");
    let (status, _) = raw(&address, &format!("GET /status HTTP/1.1\r\n{host}"), "");
    assert_eq!(status, 200, "the same request with a loopback Host");

    // Cross-site requests: a simple text/plain POST, and any foreign Origin.
    let snapshot = format!("POST /snapshot HTTP/1.1\r\n{host}");
    let (status, body) = raw(
        &address,
        &format!("{snapshot}\r\nContent-Type: text/plain"),
        "{}",
    );
    assert_eq!(status, 415, "{body}");
    assert!(body.contains("application/json"), "{body}");
    let (status, _) = raw(
        &address,
        &format!(
            "{snapshot}\r\nContent-Type: application/json\r\nOrigin: https://attacker.example"
        ),
        "{}",
    );
    assert_eq!(status, 403);
    let (status, _) = raw(
        &address,
        &format!("GET /map.vlem HTTP/1.1\r\n{host}\r\nOrigin: null"),
        "",
    );
    assert_eq!(status, 403);
    assert!(!out.join("snapshot-0001.vlem").exists());

    // Bounded queries: too many texts, or too long a text, is a 413 naming the limit.
    let many = serde_json::json!({ "texts": vec!["red"; 10_000] }).to_string();
    let (status, reply) = post(&address, "/query", &many);
    assert_eq!(status, 413, "{reply}");
    assert!(
        reply["error"].as_str().unwrap().contains("the limit is 32"),
        "{reply}"
    );
    let long = serde_json::json!({ "texts": ["r".repeat(300)] }).to_string();
    let (status, reply) = post(&address, "/query", &long);
    assert_eq!(status, 413, "{reply}");
    assert!(
        reply["error"].as_str().unwrap().contains("256 bytes"),
        "{reply}"
    );
    let (status, _) = get(&address, &format!("/heatmap.ply?text={}", "r".repeat(300)));
    assert_eq!(status, 413);

    // After all of it the run is whole and the server answers.
    wait_finished(&address);
    let (status, reply) = post(&address, "/query", r#"{"texts": ["red"]}"#);
    assert_eq!(status, 200, "{reply}");
}

/// Bytes of `head` written on a fresh connection, without a body; the first answer line's
/// status and the JSON error's message.
fn raw_head(address: &str, head: &[u8]) -> (u16, String) {
    use std::io::{Read, Write};
    let mut stream = std::net::TcpStream::connect(address).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    // The server may answer (and close) before all of an oversized head is sent.
    let _ = stream.write_all(head);
    let mut answer = Vec::new();
    let _ = stream.read_to_end(&mut answer);
    let answer = String::from_utf8_lossy(&answer).into_owned();
    let (status, body) = status_and_body(&answer);
    let message = serde_json::from_str::<serde_json::Value>(body)
        .unwrap_or_else(|_| panic!("a JSON error body: {answer}"))["error"]
        .as_str()
        .unwrap()
        .to_owned();
    (status, message)
}

/// Opens a connection and sends a POST head announcing a body it never sends.
fn stalled_post(address: &str, host: &str) -> std::net::TcpStream {
    use std::io::Write;
    let mut stream = std::net::TcpStream::connect(address).unwrap();
    write!(
        stream,
        "POST /query HTTP/1.1\r\n{host}\r\nContent-Type: application/json\r\n\
         Content-Length: 2000\r\n\r\n{{\"texts\""
    )
    .unwrap();
    stream
}

#[test]
fn oversized_stalled_and_surplus_connections_are_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let served = serve(dir.path(), &[]);
    let address = served.address.clone();
    let port = address.rsplit(':').next().unwrap();
    let host = format!("Host: 127.0.0.1:{port}");

    // Heads over the limits, and other versions of HTTP, get their statuses with a JSON message.
    let long_url = format!(
        "GET /status?{} HTTP/1.1\r\n{host}\r\n\r\n",
        "a".repeat(10_000)
    );
    let (status, message) = raw_head(&address, long_url.as_bytes());
    assert_eq!(status, 414, "{message}");
    assert!(message.contains("8192 bytes"), "{message}");
    let big_header = format!(
        "GET /status HTTP/1.1\r\n{host}\r\nX-Big: {}\r\n\r\n",
        "a".repeat(1 << 20)
    );
    let (status, message) = raw_head(&address, big_header.as_bytes());
    assert_eq!(status, 431, "{message}");
    let (status, message) = raw_head(
        &address,
        format!("GET /status HTTP/2.0\r\n{host}\r\n\r\n").as_bytes(),
    );
    assert_eq!(status, 505, "{message}");

    // HEAD gets the headers of its answer and no body: here a 405 naming the method to use.
    {
        use std::io::{Read, Write};
        let mut stream = std::net::TcpStream::connect(&address).unwrap();
        write!(
            stream,
            "HEAD /status HTTP/1.1\r\n{host}\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut answer = String::new();
        stream.read_to_string(&mut answer).unwrap();
        assert!(answer.starts_with("HTTP/1.1 405"), "{answer}");
        assert!(answer.contains("\r\nAllow: GET\r\n"), "{answer}");
        assert!(answer.ends_with("\r\n\r\n"), "no body: {answer}");
    }

    // Requests whose bodies never come hold no one up: /status and queries are answered.
    let stalled: Vec<_> = (0..8).map(|_| stalled_post(&address, &host)).collect();
    let (status, _) = get(&address, "/status");
    assert_eq!(status, 200, "status is answered beside stalled requests");
    let (status, reply) = post(&address, "/query", r#"{"texts": ["red"]}"#);
    assert_eq!(status, 200, "{reply}");

    // Connections past the cap are answered 503 by the accept loop, which goes on accepting.
    let mut idle = Vec::new();
    let refused = loop {
        use std::io::Read;
        assert!(
            idle.len() < 200,
            "the connection cap refuses some connection"
        );
        let mut stream = std::net::TcpStream::connect(&address).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_millis(100)))
            .unwrap();
        let mut first = [0u8; 12];
        match stream.read(&mut first) {
            Ok(n) if n > 0 => break String::from_utf8_lossy(&first[..n]).into_owned(),
            // Accepted and waiting for a request: an idle connection, which counts.
            _ => idle.push(stream),
        }
    };
    assert!(refused.starts_with("HTTP/1.1 503"), "{refused}");
    drop(idle);
    drop(stalled);
    // Once they close, the server answers again (connections end as their sockets close).
    let start = Instant::now();
    loop {
        let (status, _) = get(&address, "/status");
        if status == 200 {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "served again");
        std::thread::sleep(Duration::from_millis(50));
    }
    wait_finished(&address);
}

#[test]
fn a_stalled_client_does_not_keep_the_run_from_exiting() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().to_str().unwrap().to_owned();
    // Without --serve-after: the run stops serving once its outputs are written.
    let (mut child, address) = spawn_serving(&[
        "run",
        "--config",
        "configs/demo.toml",
        "--out",
        &out,
        "--serve",
        "127.0.0.1:0",
    ]);
    let port = address.rsplit(':').next().unwrap();
    let _stalled = stalled_post(&address, &format!("Host: 127.0.0.1:{port}"));
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > Duration::from_secs(180) {
            let _ = child.kill();
            panic!("vlem run still runs 180 s later, held by a stalled connection");
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(status.success(), "{status}");
    assert!(dir.path().join("map.vlem").is_file());
}

#[test]
fn a_bearer_token_is_required_when_set() {
    let dir = tempfile::tempdir().unwrap();
    let token = "0123456789abcdef0123456789abcdef";
    let served = serve(dir.path(), &["--serve-token", token]);
    let address = served.address.clone();
    let (status, body) = get(&address, "/status");
    assert_eq!(status, 401);
    assert!(
        String::from_utf8_lossy(&body).contains("Authorization: Bearer"),
        "{}",
        String::from_utf8_lossy(&body)
    );
    let mut response = agent()
        .get(format!("http://{address}/status"))
        .header("Authorization", format!("Bearer {token}"))
        .call()
        .unwrap();
    assert_eq!(response.status().as_u16(), 200);
    assert!(
        response
            .body_mut()
            .read_to_string()
            .unwrap()
            .contains("\"state\"")
    );
    // The client takes the token from the environment, as `vlem run` does.
    wait_finished_with(&address, token);
    let out = common::fails(&["query", "--connect", &address, "red"]);
    assert!(out.contains("401"), "{out}");
    let output = Command::new(env!("CARGO_BIN_EXE_vlem"))
        .args(["query", "--connect", &address, "red"])
        .env("VLEM_SERVE_TOKEN", token)
        .current_dir(repo())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(stdout.contains("30 frames integrated"), "{stdout}");
    // A token too short to be one is refused at start-up.
    let short = common::fails(&[
        "run",
        "--config",
        "configs/demo.toml",
        "--out",
        dir.path().to_str().unwrap(),
        "--serve",
        "127.0.0.1:0",
        "--serve-token",
        "secret",
    ]);
    assert!(short.contains("at least 16"), "{short}");
}

/// [`wait_finished`] for a server that requires a token.
fn wait_finished_with(address: &str, token: &str) {
    let start = Instant::now();
    loop {
        let mut response = agent()
            .get(format!("http://{address}/status"))
            .header("Authorization", format!("Bearer {token}"))
            .call()
            .unwrap();
        let value: serde_json::Value =
            serde_json::from_str(&response.body_mut().read_to_string().unwrap()).unwrap();
        if value["run"]["state"] == "finished" {
            return;
        }
        assert!(start.elapsed() < Duration::from_secs(120), "{value}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn query_connect_prints_what_query_map_prints() {
    let dir = tempfile::tempdir().unwrap();
    let served = serve(dir.path(), &[]);
    wait_finished(&served.address);
    // The run writes its outputs after the pipeline has finished.
    let map = dir.path().join("map.vlem");
    let start = Instant::now();
    while !map.exists() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "the run writes map.vlem"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let map = map.to_str().unwrap();
    for args in [
        vec!["white wall", "brown"],
        vec![
            "--segmenter",
            "cluster",
            "--baseline",
            "grey",
            "--grasp",
            "white wall",
        ],
    ] {
        let mut local = vec!["query", "--map", map];
        local.extend(&args);
        let mut remote = vec!["query", "--connect", &served.address];
        remote.extend(&args);
        let local = ok(&local);
        let remote = ok(&remote);
        // The first line names the source (a file or an address); the answers are the same.
        let answers = |out: &str| out.lines().skip(1).map(str::to_owned).collect::<Vec<_>>();
        assert!(!answers(&local).is_empty());
        assert_eq!(answers(&local), answers(&remote), "{args:?}");
        assert!(
            remote
                .lines()
                .next()
                .unwrap()
                .contains("30 frames integrated"),
            "{remote}"
        );
    }
    // A heatmap through the server is the same file as from the map.
    let local_ply = dir.path().join("local.ply");
    let remote_ply = dir.path().join("remote.ply");
    ok(&[
        "query",
        "--map",
        map,
        "--ply",
        local_ply.to_str().unwrap(),
        "brown",
    ]);
    ok(&[
        "query",
        "--connect",
        &served.address,
        "--ply",
        remote_ply.to_str().unwrap(),
        "brown",
    ]);
    assert_eq!(
        std::fs::read(local_ply).unwrap(),
        std::fs::read(remote_ply).unwrap()
    );
}

#[test]
fn serving_refuses_non_loopback_addresses_and_connect_names_the_server() {
    let dir = tempfile::tempdir().unwrap();
    let out = common::fails(&[
        "run",
        "--config",
        "configs/demo.toml",
        "--out",
        dir.path().to_str().unwrap(),
        "--serve",
        "0.0.0.0:8765",
    ]);
    assert!(out.contains("loopback only"), "{out}");
    // A port another program holds: the error says what to do, and the run leaves no empty
    // output folder behind.
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let fresh = dir.path().join("fresh");
    let out = common::fails(&[
        "run",
        "--config",
        "configs/demo.toml",
        "--out",
        fresh.to_str().unwrap(),
        "--serve",
        &taken.local_addr().unwrap().to_string(),
    ]);
    assert!(
        out.contains("another program listens on that port") && out.contains("port 0"),
        "{out}"
    );
    assert!(!fresh.exists(), "a failed start leaves no output folder");
    // Nothing listens on this port (bound and released just now).
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let address = format!("127.0.0.1:{port}");
    let out = common::fails(&["query", "--connect", &address, "red"]);
    assert!(
        out.contains(&format!("cannot reach the vlem server at {address}")),
        "{out}"
    );
}
