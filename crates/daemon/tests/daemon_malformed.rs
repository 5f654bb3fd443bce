//! 1000 malformed requests — random bytes, broken JSON, unknown commands, invalid plans,
//! oversized lines: each gets an error reply, the connection and the daemon stay up, and a
//! run then completes (issue #7).

mod daemon_support;

use daemon_support::*;
use rand::{Rng, SeedableRng};
use std::time::{Duration, Instant};

#[test]
fn a_thousand_malformed_requests_each_get_an_error_and_the_daemon_stays_up() {
    hard_timeout(60);
    let dir = temp_dir("bad");
    let d = Daemon::start(&dir);
    d.wait_ready();
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let broken_json = [
        "{",
        "{\"cmd\":",
        "{\"cmd\":\"status\"",
        "[",
        "nul",
        "{\"cmd\" \"status\"}",
        "\"cmd\"",
        "{'cmd':'status'}",
        "{\"cmd\":\"status\",}",
    ];
    let bad_requests = [
        "{}",
        "[]",
        "42",
        "null",
        "\"status\"",
        "{\"cmd\":7}",
        "{\"cmd\":\"fly\"}",
        "{\"cmd\":\"STATUS\"}",
        "{\"cmd\":\"status\",\"x\":1}",
        "{\"cmd\":\"submit\"}",
        "{\"cmd\":\"submit\",\"plan\":3}",
        "{\"cmd\":\"result\"}",
        "{\"cmd\":\"result\",\"id\":\"../../etc\"}",
        "{\"cmd\":\"result\",\"id\":\"nope\"}",
        "{\"cmd\":\"abort\"}",
        "{\"cmd\":\"abort\",\"id\":\"nope\"}",
        "",
    ];
    let bad_plans = [
        "[run]\nperiods = 0\n",
        "[run]\nband_hz = [2000.0, 1.0]\n",
        "[run]\nforce_rms_nn = 9.0\n",
        "[run]\norder = \"three\"\n",
        "[run]\nmax_iterations = -1\n",
        "[run]\nbogus = 1\n",
        "[twin]\nseed = 2\n",
        "seed = \"x\"\n",
        "name = \"../escape\"\n",
        "[run\n",
        "[run]\nmiic = 3\n",
        "[run]\nreference = \"guessed\"\n",
    ];
    let mut client = d.client();
    let mut codes = std::collections::BTreeMap::<String, usize>::new();
    let t0 = Instant::now();
    for i in 0..1000 {
        if i % 100 == 99 {
            // Some on fresh connections too.
            client = d.client();
        }
        let line: Vec<u8> = match i % 5 {
            0 => {
                let n = rng.random_range(1..300);
                (0..n)
                    .map(|_| rng.random::<u8>())
                    .map(|b| if b == b'\n' { b' ' } else { b })
                    .collect()
            }
            1 => broken_json[i % broken_json.len()].as_bytes().to_vec(),
            2 => bad_requests[i % bad_requests.len()].as_bytes().to_vec(),
            3 => serde_json::json!({"cmd": "submit", "plan": bad_plans[i % bad_plans.len()]})
                .to_string()
                .into_bytes(),
            _ if i % 50 == 4 => {
                // Oversized: just over 1 MiB, no newline inside.
                let mut v = b"{\"cmd\":\"submit\",\"plan\":\"".to_vec();
                v.resize((1 << 20) + 10, b'a');
                v
            }
            _ => format!("{{\"cmd\":\"{}\"}}", "x".repeat(i % 97 + 1)).into_bytes(),
        };
        let reply = client
            .raw(&line)
            .unwrap_or_else(|e| panic!("request {i} got no reply: {e}\nlog:\n{}", d.log()));
        assert_eq!(reply["ok"], false, "request {i} accepted: {reply}");
        let code = reply["error"].as_str().unwrap().to_string();
        assert!(!reply["message"].as_str().unwrap().is_empty());
        if code == "invalid_plan" && i < 60 {
            eprintln!("  e.g. {}", reply["message"]);
        }
        *codes.entry(code).or_default() += 1;
    }
    eprintln!("1000 malformed requests in {:?}: {codes:?}", t0.elapsed());
    assert!(codes.contains_key("too_large"));
    assert!(codes.contains_key("invalid_plan"));
    assert!(codes.contains_key("bad_json"));
    // The same connection still works, and so does a run.
    assert_eq!(client.raw(br#"{"cmd":"ping"}"#).unwrap()["ok"], true);
    let id = d.submit("");
    let r = d.wait_result(&id, Duration::from_secs(30));
    assert_eq!(r["status"], "completed", "{}", r["error"]);
    drop(d);
    std::fs::remove_dir_all(&dir).unwrap();
}
