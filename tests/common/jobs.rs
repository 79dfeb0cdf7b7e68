//! Watching an orchestrator's jobs from a test: listing (through any of several URLs, as the
//! CLI does), waiting with a bound for a condition on the list, and what a job is called.

use std::collections::HashMap;
use std::time::{Duration, Instant};
use wavesplat_orchestrator_client as client;
use wavesplat_orchestrator_client::convert::state_name;
use wavesplat_proto::pb;

/// Every job, through the first of `urls` (comma-separated) that answers; `None` if none does.
pub async fn list(urls: &str) -> Option<Vec<pb::Job>> {
    let mut c = client::connect(urls).await.ok()?;
    client::list(&mut c).await.ok()
}

/// A job's cache name.
pub fn name(j: &pb::Job) -> &str {
    &j.spec.as_ref().unwrap().name
}

/// How often each of `names` was delivered according to workers' logs (`log`: their text,
/// one `delivered … name=NAME …` line per delivery).
pub fn deliveries(log: &str, names: &[String]) -> HashMap<String, usize> {
    let mut count = HashMap::new();
    for line in log.lines().filter(|l| l.contains("delivered")) {
        for n in names {
            if line.contains(&format!("name={n} ")) {
                *count.entry(n.clone()).or_default() += 1;
            }
        }
    }
    count
}

/// Every job done, failed or cancelled (and at least one job).
pub fn finished(js: &[pb::Job]) -> bool {
    !js.is_empty()
        && js
            .iter()
            .all(|j| matches!(state_name(j.state), "done" | "failed" | "cancelled"))
}

/// Polls until `pred` holds for the job list, at most `secs` seconds; on timeout, panics with
/// every job's state and error.
pub async fn wait_for(
    urls: &str,
    secs: u64,
    what: &str,
    pred: impl Fn(&[pb::Job]) -> bool,
) -> Vec<pb::Job> {
    let end = Instant::now() + Duration::from_secs(secs);
    loop {
        let js = list(urls).await;
        if let Some(js) = &js {
            if pred(js) {
                return js.clone();
            }
        }
        if Instant::now() > end {
            let states: Vec<String> = js
                .unwrap_or_default()
                .iter()
                .map(|j| format!("{} {} {} {}", j.id, name(j), state_name(j.state), j.error))
                .collect();
            panic!("timed out waiting for {what}: {states:#?}");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}
