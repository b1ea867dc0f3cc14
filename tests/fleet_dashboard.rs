//! The fleet dashboard (`deploy/grafana/scanrig-fleet.json`) against the real `/metrics` text of a
//! running `scanrigd`: every metric name in every panel query (and in the `rig` variable's
//! `label_values(...)`) is exported, every label a selector matches on is on that metric's
//! samples, and every label of a `by (...)` / `ignoring (...)` list is on a metric of the query.
//! The PromQL is read by a small scanner (strings, selectors, ranges, label lists, function
//! calls, keywords); it checks names, not the queries' arithmetic.

mod daemon_common;

use std::collections::{BTreeMap, BTreeSet};

use daemon_common::{client, rig_from, spawn};

/// Metric name -> label names seen on its samples, from the Prometheus text format.
fn exported(text: &str) -> BTreeMap<String, BTreeSet<String>> {
    let mut out: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for line in text.lines().filter(|l| !l.starts_with('#') && !l.trim().is_empty()) {
        let (name, rest) = match line.find(['{', ' ']) {
            Some(i) => line.split_at(i),
            None => (line, ""),
        };
        let labels = out.entry(name.to_owned()).or_default();
        if let Some(body) = rest.strip_prefix('{').and_then(|r| r.split_once('}')).map(|(b, _)| b) {
            for pair in split_outside_quotes(body) {
                if let Some((k, _)) = pair.split_once('=') {
                    labels.insert(k.trim().to_owned());
                }
            }
        }
    }
    out
}

fn split_outside_quotes(s: &str) -> Vec<String> {
    let (mut out, mut cur, mut quoted, mut escaped) = (Vec::new(), String::new(), false, false);
    for c in s.chars() {
        match c {
            _ if escaped => escaped = false,
            '\\' if quoted => escaped = true,
            '"' => quoted = !quoted,
            ',' if !quoted => {
                out.push(std::mem::take(&mut cur));
                continue;
            }
            _ => {}
        }
        cur.push(c);
    }
    if !cur.trim().is_empty() {
        out.push(cur);
    }
    out
}

/// What a query names.
#[derive(Debug, Default)]
struct Names {
    /// Metric -> labels its selector matches on.
    metrics: Vec<(String, Vec<String>)>,
    /// Labels of `by`, `without`, `on`, `ignoring`, `group_left`, `group_right` lists.
    grouping: Vec<String>,
}

const KEYWORDS: &[&str] =
    &["by", "without", "on", "ignoring", "group_left", "group_right", "bool", "and", "or", "unless", "offset"];

/// Aggregation operators, which may be followed by `by (...)` before their parenthesis.
const AGGREGATIONS: &[&str] =
    &["sum", "min", "max", "avg", "group", "stddev", "stdvar", "count", "count_values", "bottomk", "topk", "quantile"];

fn scan_query(q: &str) -> Names {
    let b: Vec<char> = q.chars().collect();
    let mut names = Names::default();
    let mut i = 0;
    let ident = |c: char| c.is_ascii_alphanumeric() || c == '_' || c == ':';
    while i < b.len() {
        let c = b[i];
        if c == '"' {
            i += 1;
            while i < b.len() && b[i] != '"' {
                i += if b[i] == '\\' { 2 } else { 1 };
            }
            i += 1;
        } else if c == '[' {
            while i < b.len() && b[i] != ']' {
                i += 1;
            }
            i += 1;
        } else if c.is_ascii_digit() {
            while i < b.len() && (ident(b[i]) || b[i] == '.') {
                i += 1;
            }
        } else if ident(c) {
            let start = i;
            while i < b.len() && ident(b[i]) {
                i += 1;
            }
            let word: String = b[start..i].iter().collect();
            let mut j = i;
            while j < b.len() && b[j] == ' ' {
                j += 1;
            }
            let next = b.get(j).copied();
            if KEYWORDS.contains(&word.as_str()) {
                if next == Some('(') {
                    let close = b[j..].iter().position(|&c| c == ')').map_or(b.len(), |p| j + p);
                    let list: String = b[j + 1..close].iter().collect();
                    names.grouping.extend(list.split(',').map(|s| s.trim().to_owned()).filter(|s| !s.is_empty()));
                    i = close + 1;
                }
            } else if next == Some('(') || AGGREGATIONS.contains(&word.as_str()) {
                // A function call or an aggregation (`sum by (rig) (...)`): its arguments are
                // scanned as they come.
            } else {
                let mut labels = Vec::new();
                if next == Some('{') {
                    let mut k = j + 1;
                    let mut quoted = false;
                    let mut body = String::new();
                    while k < b.len() && (quoted || b[k] != '}') {
                        if b[k] == '"' && (k == 0 || b[k - 1] != '\\') {
                            quoted = !quoted;
                        }
                        body.push(b[k]);
                        k += 1;
                    }
                    for m in split_outside_quotes(&body) {
                        let key: String = m.chars().take_while(|&c| ident(c)).collect();
                        labels.push(key);
                    }
                    i = k + 1;
                }
                names.metrics.push((word, labels));
            }
        } else {
            i += 1;
        }
    }
    names
}

fn queries(dashboard: &serde_json::Value) -> Vec<String> {
    let mut out = Vec::new();
    for p in dashboard["panels"].as_array().expect("panels") {
        for t in p["targets"].as_array().expect("targets") {
            out.push(t["expr"].as_str().expect("expr").to_owned());
        }
    }
    out
}

#[test]
fn the_query_scanner_finds_names_and_labels() {
    let n = scan_query(
        r#"sum by (rig, stage) (increase(a_total{rig=~"$rig",stage!="x,}"}[6h])) / ignoring (stage) group_left sum by (rig) (rate(b[5m])) * 60"#,
    );
    assert_eq!(
        n.metrics,
        vec![("a_total".to_owned(), vec!["rig".to_owned(), "stage".to_owned()]), ("b".to_owned(), vec![])]
    );
    assert_eq!(n.grouping, vec!["rig", "stage", "stage", "rig"]);
}

#[test]
fn every_dashboard_query_names_metrics_and_labels_the_daemon_exports() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_from(dir.path(), "simulated.toml", &[]);
    let state = dir.path().join("state");
    std::fs::create_dir_all(&state).expect("state dir");
    let d = spawn(&rig, &state);
    let text = String::from_utf8(client(&d).request("GET", "/metrics", None).expect("metrics").body).expect("utf8");
    let exported = exported(&text);
    let rig_name = std::fs::read_to_string(&rig).expect("rig");
    let name_line = rig_name.lines().find(|l| l.trim_start().starts_with("name")).expect("[rig] name");
    let name = name_line.split('"').nth(1).expect("quoted name");
    assert!(text.contains(&format!("scanrig_scans_started_total{{rig=\"{name}\"}} 0\n")), "{text}");
    for m in ["scanrig_replication_queued", "scanrig_replication_bytes_total", "scanrig_replication_failures_total"] {
        assert!(exported.contains_key(m), "{m} missing from {text}");
    }

    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/grafana/scanrig-fleet.json");
    let dashboard: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&path).expect("dashboard")).expect("dashboard JSON");
    let mut checked = 0;
    let mut all = queries(&dashboard);
    for v in dashboard["templating"]["list"].as_array().expect("templating") {
        if let Some(q) = v["query"]["query"].as_str() {
            // label_values(METRIC, LABEL): the metric must carry the label.
            let inner = q.strip_prefix("label_values(").and_then(|r| r.strip_suffix(')')).expect("label_values");
            let (metric, label) = inner.split_once(',').expect("metric, label");
            let labels = exported.get(metric.trim()).unwrap_or_else(|| panic!("{metric} is not exported"));
            assert!(labels.contains(label.trim()), "{metric} has no label {label}");
            all.push(metric.trim().to_owned());
        }
    }
    assert!(all.len() >= 10, "too few queries: {all:?}");
    for q in &all {
        let names = scan_query(q);
        assert!(!names.metrics.is_empty(), "no metric in `{q}`");
        let mut labels_here = BTreeSet::new();
        for (metric, labels) in &names.metrics {
            let have = exported.get(metric).unwrap_or_else(|| panic!("`{q}`: {metric} is not in /metrics:\n{text}"));
            for l in labels {
                assert!(have.contains(l), "`{q}`: {metric} has no label `{l}` (it has {have:?})");
            }
            labels_here.extend(have.iter().cloned());
            checked += 1;
        }
        for l in &names.grouping {
            assert!(labels_here.contains(l), "`{q}`: no metric of the query has the label `{l}`");
        }
    }
    assert!(checked >= 12, "{checked}");
}
