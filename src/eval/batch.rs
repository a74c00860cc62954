//! Scenario batches, shared by `b2dr sim` and `b2dr run` (spec loop.md section 3): the scenario list in name
//! order and its shards (`--shard K/N`), the output folder's `config.json` and the `--resume` check, the loop
//! over scenarios (one folder per scenario, its `metrics.json` written last marks it done), the summary (CLS,
//! per-metric means, per-stage timing totals), and `b2dr merge` of shard folders into one summary.
//!
//! The summary of a merge equals the summary of the single run over the same scenarios in everything that is
//! deterministic (the CLS, the per-metric means and each scenario's entry, bit for bit); only timings differ,
//! as they do between two single runs. Both order the scenarios by folder name and sum in that order.
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context as _, Result};
use serde_json::{json, Map, Value};

use crate::scene::import::Source;

/// The nuPlan metrics whose means over scenarios the summary carries (plus `score`, the CLS).
pub const METRICS: [&str; 8] = [
    "no_ego_at_fault_collisions",
    "drivable_area_compliance",
    "driving_direction_compliance",
    "ego_is_making_progress",
    "time_to_collision_within_bound",
    "speed_limit_compliance",
    "ego_progress_along_expert_route",
    "ego_is_comfortable",
];

/// `--shard K/N`: this process runs every N-th scenario of the name-ordered list, starting at the K-th
/// (0-based: K in 0..N, as SLURM_ARRAY_TASK_ID of `--array=0-(N-1)` and JOB_COMPLETION_INDEX count).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl std::str::FromStr for Shard {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        let Some((k, n)) = s.split_once('/') else {
            bail!("--shard {s:?}: expected K/N (shard K of N, 0 <= K < N), e.g. 0/3");
        };
        let num = |x: &str, what: &str| -> Result<usize> {
            x.trim().parse::<usize>().map_err(|_| {
                anyhow::anyhow!("--shard {s:?}: {what} {x:?} is not a non-negative integer")
            })
        };
        let (index, count) = (num(k, "K")?, num(n, "N")?);
        ensure!(count >= 1, "--shard {s:?}: N must be at least 1");
        ensure!(
            index < count,
            "--shard {s:?}: K must be in 0..{count} (0-based: the shards of {count} are 0/{count} .. {}/{count})",
            count - 1
        );
        Ok(Self { index, count })
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl Shard {
    /// Deals an ordered list round-robin: this shard's items are those at positions index, index + count, ...
    pub fn deal<T>(&self, items: Vec<T>) -> Vec<T> {
        items
            .into_iter()
            .enumerate()
            .filter(|(i, _)| i % self.count == self.index)
            .map(|(_, t)| t)
            .collect()
    }
}

/// A folder name from a scenario name (no separators or dots that could leave `--out`).
pub fn folder_name(name: &str) -> String {
    crate::scene::safe_name(name)
}

/// The scenarios in folder-name order (two scenarios with one folder are refused), then `shard`'s part.
pub fn select(mut sources: Vec<Source>, shard: Option<Shard>) -> Result<Vec<Source>> {
    sources.sort_by_cached_key(|s| folder_name(&s.name()));
    for w in sources.windows(2) {
        let (a, b) = (folder_name(&w[0].name()), folder_name(&w[1].name()));
        ensure!(
            a != b,
            "--scenario: {} and {} both write the folder {a:?} (a scenario listed twice?)",
            w[0].name(),
            w[1].name()
        );
    }
    Ok(match shard {
        Some(s) => s.deal(sources),
        None => sources,
    })
}

/// Writes a file through a temporary one and a rename (a reader never sees half a file).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path)
        .with_context(|| format!("renaming {} to {}", tmp.display(), path.display()))
}

/// Key of `config.json` holding the content fingerprints of the files the batch reads ([`with_inputs`]).
pub const INPUTS_KEY: &str = "input_files";

/// Content fingerprint of a file: its size and its XXH3-128 (xxhash-rust, streamed in 1 MiB blocks: memory
/// bandwidth, so multi-GB nuPlan DBs are hashed in seconds). Detects any change of content (with 2^-128 odds of
/// missing one), not an adversary.
pub fn file_fingerprint(path: &Path) -> Result<Value> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).with_context(|| format!("hashing {}", path.display()))?;
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut size = 0u64;
    loop {
        let n = f
            .read(&mut buf)
            .with_context(|| format!("hashing {}", path.display()))?;
        if n == 0 {
            break;
        }
        size += n as u64;
        h.update(&buf[..n]);
    }
    Ok(json!({"size": size, HASH_KEY: format!("{:032x}", h.digest128())}))
}

/// The hash field of a fingerprint ([`file_fingerprint`]).
pub const HASH_KEY: &str = "xxh3_128";

/// The files a planner command line reads that can be named: every word of it (split at blanks, quotes
/// removed) that names an existing regular file, e.g. the script of `python3 planner.py --weights w.pt` and its
/// weights. `python -m module` planners name no file.
pub fn planner_files(planner: &str) -> Vec<PathBuf> {
    let Some(cmd) = planner.strip_prefix("cmd:") else {
        return vec![];
    };
    cmd.split_whitespace()
        .map(|w| w.trim_matches(|c| c == '"' || c == '\'').to_string())
        .flat_map(|w| {
            // `--flag=FILE` names FILE
            let tail = w.split_once('=').map(|(_, t)| t.to_string());
            [Some(w), tail]
        })
        .flatten()
        .map(PathBuf::from)
        .filter(|p| p.is_file())
        .collect()
}

/// `config` with [`INPUTS_KEY`]: the fingerprint ([`file_fingerprint`]) of every file the scenarios are read
/// from (a ScenarioNet file; a nuScenes scene's tables and map expansion; a nuPlan log DB and its map) and of
/// every file the planner command names ([`planner_files`]) and of the `model` files (the renderer's package,
/// [`crate::render::package::package_files`]), by path, so that `--resume` refuses a folder whose inputs changed
/// since (naming the file). Built-in scenarios read no file. Camera images are not hashed: a log's images are
/// many GB (a nuPlan log's sensor_blobs: tens of GB), the tables that name them (path, timestamp, pose) are
/// hashed; an image edited in place under the same name goes unnoticed. A file that cannot be read is recorded
/// as such (`"unreadable"`: its scenario fails on its own, scoring 0, as before), so that it becoming readable is
/// a change too.
pub fn with_inputs(
    mut config: Value,
    sources: &[Source],
    planner: &str,
    model: &[PathBuf],
) -> Result<Value> {
    let mut files: Vec<(String, PathBuf)> = vec![];
    let mut inputs = Map::new();
    for s in sources {
        let paths = match s {
            Source::Builtin(_) => vec![],
            Source::File(p) => vec![p.clone()],
            Source::Nuscenes(n) => n.input_files(),
            Source::Nuplan(n) => match n.input_files() {
                Ok(v) => v,
                Err(e) => {
                    inputs.insert(
                        n.db.display().to_string(),
                        json!({"role": "scenario", "unreadable": format!("{e:#}")}),
                    );
                    vec![]
                }
            },
        };
        files.extend(paths.into_iter().map(|p| ("scenario".to_string(), p)));
    }
    files.extend(
        planner_files(planner)
            .into_iter()
            .map(|p| ("planner".to_string(), p)),
    );
    files.extend(model.iter().map(|p| ("model".to_string(), p.clone())));
    for (role, p) in files {
        let key = p.display().to_string();
        if inputs.contains_key(&key) {
            continue;
        }
        let mut fp =
            file_fingerprint(&p).unwrap_or_else(|e| json!({"unreadable": format!("{e:#}")}));
        fp["role"] = json!(role);
        inputs.insert(key, fp);
    }
    if let Some(o) = config.as_object_mut() {
        o.insert(INPUTS_KEY.into(), Value::Object(inputs));
    }
    Ok(config)
}

/// How the input files of two configurations differ, naming each changed, added or removed file (None: same).
fn inputs_difference(old: &Value, new: &Value) -> Option<String> {
    let empty = Map::new();
    let (a, b) = (
        old.get(INPUTS_KEY)
            .and_then(Value::as_object)
            .unwrap_or(&empty),
        new.get(INPUTS_KEY)
            .and_then(Value::as_object)
            .unwrap_or(&empty),
    );
    let what = |v: &Value| match v["unreadable"].as_str() {
        Some(why) => format!("unreadable: {why}"),
        None => match v[HASH_KEY].as_str() {
            Some(h) => format!("{} bytes, {HASH_KEY} {h}", v["size"]),
            // a folder begun by an older b2dr (another hash): reported as a change, never matched
            None => format!("{} bytes, a fingerprint of an older b2dr", v["size"]),
        },
    };
    let mut out = vec![];
    for (k, v) in b {
        match a.get(k) {
            Some(o) if o == v => {}
            Some(o) => out.push(format!(
                "the {} {k} changed since the run began (then {}; now {})",
                v["role"].as_str().unwrap_or("input"),
                what(o),
                what(v)
            )),
            None => out.push(format!(
                "the {} {k} ({}) was not an input of the run",
                v["role"].as_str().unwrap_or("input"),
                what(v)
            )),
        }
    }
    for (k, o) in a {
        if !b.contains_key(k) {
            out.push(format!(
                "the {} {k} ({}) is no longer an input",
                o["role"].as_str().unwrap_or("input"),
                what(o)
            ));
        }
    }
    (!out.is_empty()).then(|| out.join("; "))
}

fn read_json(path: &Path) -> Result<Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: not valid JSON", path.display()))
}

/// The top-level fields where two configurations differ, as "field: a vs b; ..." (None: equal).
fn config_difference(a: &Value, b: &Value, ignore: &[&str]) -> Option<String> {
    let empty = Map::new();
    let (ma, mb) = (
        a.as_object().unwrap_or(&empty),
        b.as_object().unwrap_or(&empty),
    );
    let mut keys: Vec<&String> = ma.keys().chain(mb.keys()).collect();
    keys.sort();
    keys.dedup();
    let diffs: Vec<String> = keys
        .into_iter()
        .filter(|k| !ignore.contains(&k.as_str()))
        .filter_map(|k| {
            let (x, y) = (
                ma.get(k).unwrap_or(&Value::Null),
                mb.get(k).unwrap_or(&Value::Null),
            );
            (x != y).then(|| format!("{k}: {x} vs {y}"))
        })
        .collect();
    (!diffs.is_empty()).then(|| diffs.join("; "))
}

/// Prepares `out` for a batch: with `resume`, a `config.json` there of another configuration is refused
/// (naming the first differing field); then the configuration is written and the previous summary removed (a
/// folder without `metrics.json` is an unfinished run, which `merge` refuses).
pub fn prepare_out(out: &Path, config: &Value, resume: bool) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let cpath = out.join("config.json");
    if resume && !cpath.is_file() {
        // results without the configuration that made them cannot be checked: refuse to reuse them
        if let Some(done) = finished_scenario(out)? {
            bail!(
                "--resume: {} holds results ({}) but no config.json, so whether they were made with this                  planner and agents cannot be checked; delete the folder or rerun without --resume",
                out.display(),
                done.display()
            );
        }
    }
    if resume && cpath.is_file() {
        let old = read_json(&cpath)?;
        if let Some(d) = config_difference(&old, config, &[INPUTS_KEY]) {
            bail!(
                "--resume: {} was written by another configuration ({d}); delete the folder or use the same flags:\n  \
                 before: {old}\n  now:    {config}",
                cpath.display()
            );
        }
        if let Some(d) = inputs_difference(&old, config) {
            bail!(
                "--resume: {}: {d}; the results there may not be those of these inputs: delete the folder or \
                 rerun without --resume",
                cpath.display()
            );
        }
    }
    write_atomic(&cpath, serde_json::to_string_pretty(config)?.as_bytes())?;
    let summary = out.join("metrics.json");
    if summary.is_file() {
        std::fs::remove_file(&summary)
            .with_context(|| format!("removing the old {}", summary.display()))?;
    }
    Ok(())
}

/// A scenario folder of `out` holding a `metrics.json`, if any.
fn finished_scenario(out: &Path) -> Result<Option<PathBuf>> {
    let entries = std::fs::read_dir(out).with_context(|| format!("reading {}", out.display()))?;
    for e in entries {
        let p = e
            .with_context(|| format!("reading {}", out.display()))?
            .path()
            .join("metrics.json");
        if p.is_file() {
            return Ok(Some(p));
        }
    }
    Ok(None)
}

/// Refuses an `out` folder that holds (or is) the folder of a scenario file: the batch's own `config.json` and
/// `metrics.json` would be read back as scenarios by the next run over that folder.
pub fn check_out_outside_scenarios(out: &Path, sources: &[Source]) -> Result<()> {
    let canon = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let out_c = canon(out);
    for s in sources {
        if let Source::File(f) = s {
            let parent = f.parent().filter(|p| !p.as_os_str().is_empty());
            let dir = canon(parent.unwrap_or(Path::new(".")));
            ensure!(
                !dir.starts_with(&out_c),
                "--out {} holds the scenario file {}: its config.json and metrics.json would be read as                  scenarios by the next run over that folder; give an --out outside the scenario folder",
                out.display(),
                f.display()
            );
        }
    }
    Ok(())
}

/// Fails (for a non-zero exit status) when every scenario of a summary failed; the summary is written
/// first, so the failures stay readable in `metrics.json`.
pub fn ensure_not_all_failed(summary: &Value, out: &Path) -> Result<()> {
    let n = summary["scenarios"].as_array().map_or(0, |v| v.len());
    let failures = summary["failures"].as_u64().unwrap_or(0) as usize;
    if n > 0 && failures == n {
        let first = summary["scenarios"][0]["failure"]
            .as_str()
            .unwrap_or("")
            .to_string();
        bail!(
            "every scenario failed ({failures} of {n}; see {}); the first: {first}",
            out.join("metrics.json").display()
        );
    }
    Ok(())
}

/// One line per finished scenario: "name: score 0.9123" and the failure, if any.
pub fn score_line(name: &str, v: &Value) -> String {
    format!(
        "{name}: score {:.4}{}",
        v["score"].as_f64().unwrap_or(0.0),
        v["failure"]
            .as_str()
            .map(|f| format!(" (failed: {f})"))
            .unwrap_or_default()
    )
}

/// Runs `run_one(position, source, folder)` for each scenario into `out/<folder>/`; with `resume`, a scenario
/// whose `metrics.json` exists is read back instead. A scenario that fails to load or write is recorded as a
/// failure (score 0) and the batch goes on. `report` sees each scenario's value once it is done.
pub fn for_each_scenario(
    out: &Path,
    sources: &[Source],
    resume: bool,
    mut run_one: impl FnMut(usize, &Source, &Path) -> Result<Value>,
    mut report: impl FnMut(&str, &Value),
) -> Result<Vec<Value>> {
    let mut results = Vec::with_capacity(sources.len());
    for (i, src) in sources.iter().enumerate() {
        let name = src.name();
        let dir = out.join(folder_name(&name));
        let done = dir.join("metrics.json");
        let v = if resume && done.is_file() {
            read_json(&done).context("delete it to rerun the scenario")?
        } else {
            match run_one(i, src, &dir) {
                Ok(v) => v,
                Err(e) => {
                    let v = json!({ "scenario": name, "failure": format!("{e:#}"), "score": 0.0 });
                    std::fs::create_dir_all(&dir).ok();
                    write_atomic(&done, serde_json::to_string_pretty(&v)?.as_bytes())?;
                    v
                }
            }
        };
        report(&name, &v);
        results.push(v);
    }
    Ok(results)
}

/// The summary of scenario results: `header`'s fields, then `cls` (the mean score), `metric_means`,
/// `timing_ms` (per-stage totals of the scenarios' `timing_ms`, plus `wall`: the scenarios' `wall_ms`) and
/// `scenarios`. Scenarios are put in folder-name order first, so the sums do not depend on how they were run.
pub fn summarize(header: Map<String, Value>, mut results: Vec<Value>) -> Value {
    results.sort_by_cached_key(order_key);
    let n = results.len();
    let mean = |f: &dyn Fn(&Value) -> f64| -> f64 {
        if n == 0 {
            0.0
        } else {
            results.iter().map(f).sum::<f64>() / n as f64
        }
    };
    let cls = mean(&|v| v["score"].as_f64().unwrap_or(0.0));
    let mut means = Map::new();
    for k in METRICS {
        means.insert(
            k.to_string(),
            json!(mean(&|v| v["metrics"][k].as_f64().unwrap_or(0.0))),
        );
    }
    let mut timing: Vec<(String, f64)> = vec![];
    let mut add = |k: &str, x: f64| match timing.iter_mut().find(|(n, _)| n == k) {
        Some(e) => e.1 += x,
        None => timing.push((k.to_string(), x)),
    };
    for v in &results {
        if let Some(t) = v["timing_ms"].as_object() {
            for (k, x) in t {
                add(k, x.as_f64().unwrap_or(0.0));
            }
        }
        if let Some(w) = v["wall_ms"].as_f64() {
            add("wall", w);
        }
    }
    let failures = results.iter().filter(|v| !v["failure"].is_null()).count();
    let mut s = header;
    s.insert("cls".into(), json!(cls));
    s.insert("metric_means".into(), Value::Object(means));
    s.insert("failures".into(), json!(failures));
    s.insert(
        "timing_ms".into(),
        Value::Object(timing.into_iter().map(|(k, v)| (k, json!(v))).collect()),
    );
    s.insert("scenarios".into(), Value::Array(results));
    Value::Object(s)
}

/// Where a scenario's entry goes in a summary: its folder name, then its source (two scenario files may carry
/// one scenario name).
fn order_key(v: &Value) -> (String, String) {
    (
        folder_name(v["scenario"].as_str().unwrap_or("")),
        v["source"].to_string(),
    )
}

/// Writes `<out>/metrics.json`.
pub fn write_summary(out: &Path, summary: &Value) -> Result<()> {
    write_atomic(
        &out.join("metrics.json"),
        serde_json::to_string_pretty(summary)?.as_bytes(),
    )
}

/// The fields of a batch summary that are not per-scenario results (everything but those `summarize` adds).
fn header_of(summary: &Value) -> Map<String, Value> {
    let mut h = summary.as_object().cloned().unwrap_or_default();
    for k in ["cls", "metric_means", "failures", "timing_ms", "scenarios"] {
        h.remove(k);
    }
    h
}

/// `b2dr merge DIR... --out OUT`: the shard folders of one configuration (each with its `config.json` and
/// `metrics.json`, i.e. finished) into one summary in `OUT/metrics.json` (and `OUT/config.json`: the shards'
/// configuration without the shard). Refused, naming the cause: folders of different configurations (the
/// first differing field), an unfinished shard, shards of different counts, a shard given twice or missing,
/// a scenario in two shards. Per-scenario folders stay where they are; the summary lists the shard folders.
pub fn merge(dirs: &[PathBuf], out: &Path) -> Result<Value> {
    ensure!(!dirs.is_empty(), "merge: no shard folder given");
    let canon = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    ensure!(
        !dirs.iter().any(|d| canon(d) == canon(out)),
        "merge: --out {} is one of the shard folders; give a new folder",
        out.display()
    );
    let mut first: Option<(PathBuf, Value)> = None;
    // union of the shards' input files; one file with two fingerprints is an error
    let mut inputs = Map::new();
    // shard index -> folder, and N: a map, so that an N read from a file sizes nothing
    let mut seen: std::collections::BTreeMap<usize, PathBuf> = Default::default();
    let mut count: Option<usize> = None;
    let mut results: Vec<Value> = vec![];
    let mut header: Option<Map<String, Value>> = None;
    let mut shards = vec![];
    let mut devices: Vec<Value> = vec![];
    for d in dirs {
        let cpath = d.join("config.json");
        ensure!(
            cpath.is_file(),
            "merge: {} has no config.json (not an output folder of `b2dr sim` or `b2dr run`)",
            d.display()
        );
        let cfg = read_json(&cpath)?;
        if let Some(m) = cfg.get(INPUTS_KEY).and_then(Value::as_object) {
            for (k, v) in m {
                match inputs.get(k) {
                    Some(o) if o != v => bail!(
                        "merge: {}: the input file {k} differs from another shard's ({v} vs {o}): it changed \
                         between the shards' runs",
                        cpath.display()
                    ),
                    Some(_) => {}
                    None => {
                        inputs.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        let spath = d.join("metrics.json");
        ensure!(
            spath.is_file(),
            "merge: {} is unfinished (no metrics.json); rerun its shard with the same flags and --resume",
            d.display()
        );
        let summary = read_json(&spath)?;
        let shard: Shard = match cfg.get("shard") {
            None | Some(Value::Null) => Shard { index: 0, count: 1 },
            Some(s) => serde_json::from_value(s.clone())
                .with_context(|| format!("merge: {}: invalid \"shard\"", cpath.display()))?,
        };
        // the file is data: a shard K/N read back must be one `--shard` accepts
        ensure!(
            shard.count >= 1 && shard.index < shard.count,
            "merge: {}: \"shard\" {}/{} is not a shard K/N with 0 <= K < N",
            cpath.display(),
            shard.index,
            shard.count
        );
        match &first {
            None => first = Some((d.clone(), cfg.clone())),
            Some((d0, c0)) => {
                if let Some(diff) = config_difference(c0, &cfg, &["shard", INPUTS_KEY]) {
                    bail!(
                        "merge: {} and {} are runs of different configurations ({diff}); only shards of one \
                         configuration merge",
                        d0.display(),
                        d.display()
                    );
                }
            }
        }
        let n = *count.get_or_insert(shard.count);
        ensure!(
            n == shard.count,
            "merge: {} is shard {shard} but {} was cut into {} shards",
            d.display(),
            first
                .as_ref()
                .map(|f| f.0.display().to_string())
                .unwrap_or_default(),
            n
        );
        if let Some(prev) = seen.get(&shard.index) {
            bail!(
                "merge: shard {shard} is given twice ({} and {})",
                prev.display(),
                d.display()
            );
        }
        seen.insert(shard.index, d.clone());
        let h = header_of(&summary);
        let mut h_cmp = h.clone();
        if let Some(dev) = h_cmp.remove("device") {
            if !devices.contains(&dev) {
                devices.push(dev);
            }
        }
        h_cmp.remove("device_bytes");
        match &header {
            None => header = Some(h_cmp),
            Some(h0) => {
                if let Some(diff) =
                    config_difference(&Value::Object(h0.clone()), &Value::Object(h_cmp), &[])
                {
                    bail!(
                        "merge: {}'s metrics.json differs from the other shards' ({diff})",
                        d.display()
                    );
                }
            }
        }
        let sc = summary["scenarios"]
            .as_array()
            .with_context(|| format!("merge: {}: no \"scenarios\" list", spath.display()))?;
        shards.push(
            json!({"folder": d, "shard": shard.to_string(), "scenarios": sc.len(),
            "device": h.get("device"), "device_bytes": h.get("device_bytes")}),
        );
        results.extend(sc.iter().cloned());
    }
    let n = count.unwrap_or(0);
    // the first few missing shards (N may be huge: the scan stops after 10 of them)
    let missing: Vec<String> = (0..n)
        .filter(|i| !seen.contains_key(i))
        .take(10)
        .map(|i| format!("{i}/{n}"))
        .collect();
    let more = (n - seen.len()).saturating_sub(missing.len());
    ensure!(
        missing.is_empty(),
        "merge: shard(s) {}{} missing (every shard of --shard K/N must be given)",
        missing.join(", "),
        if more > 0 {
            format!(" and {more} more")
        } else {
            String::new()
        }
    );
    let mut keys: Vec<(String, String)> = results.iter().map(order_key).collect();
    keys.sort_unstable();
    if let Some(w) = keys.windows(2).find(|w| w[0] == w[1]) {
        bail!("merge: scenario {} is in more than one shard", w[0].0);
    }
    let mut header = header.unwrap_or_default();
    // one device for all shards: the single run's field; several: the list
    if let Some(dev) = match devices.len() {
        0 => None,
        1 => devices.pop(),
        _ => Some(Value::Array(devices)),
    } {
        header.insert("device".into(), dev);
    }
    header.insert("merged_from".into(), Value::Array(shards));
    let summary = summarize(header, results);
    let (_, mut cfg) = first.context("merge: no shard")?;
    if let Some(o) = cfg.as_object_mut() {
        o.remove("shard");
        o.insert(INPUTS_KEY.into(), Value::Object(inputs));
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write_atomic(
        &out.join("config.json"),
        serde_json::to_string_pretty(&cfg)?.as_bytes(),
    )?;
    write_summary(out, &summary)?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A config.json whose "shard" is not one `--shard` accepts (N = 0, K >= N, N = 10^18) is an error naming
    /// the file, not an index panic or a 10^18-entry allocation (issue #18).
    #[test]
    fn merge_refuses_hostile_shard_fields() {
        let root = std::env::temp_dir().join(format!("b2dr_merge_hostile_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let d = root.join("shard");
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(d.join("metrics.json"), r#"{"scenarios": []}"#).unwrap();
        for (shard, needle) in [
            (json!({"index": 0, "count": 0}), "0 <= K < N"),
            (json!({"index": 5, "count": 2}), "0 <= K < N"),
            (
                json!({"index": 0, "count": 1_000_000_000_000_000_000u64}),
                "10/1000000000000000000 and 999999999999999989 more missing",
            ),
        ] {
            let cfg = json!({"command": "sim", "shard": shard});
            std::fs::write(d.join("config.json"), cfg.to_string()).unwrap();
            let e = format!(
                "{:#}",
                merge(std::slice::from_ref(&d), &root.join("out")).unwrap_err()
            );
            assert!(e.contains(needle) && e.contains("shard"), "{shard}: {e}");
        }
        std::fs::remove_dir_all(&root).ok();
    }
}
