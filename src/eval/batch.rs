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

/// The names of every scenario of a batch in folder-name order, before the shards are dealt (`config.json`'s
/// [`LIST_KEY`]): what `merge` checks each shard's scenarios against (issue #36).
#[derive(Clone, Debug, PartialEq)]
pub struct ScenarioList(pub Vec<String>);

/// Key of `config.json` holding the batch's whole scenario list ([`ScenarioList`]).
pub const LIST_KEY: &str = "scenario_list";

/// [`select`], also returning the whole list's names (before the shard is dealt).
pub fn select_listed(
    sources: Vec<Source>,
    shard: Option<Shard>,
) -> Result<(Vec<Source>, ScenarioList)> {
    let all = select(sources, None)?;
    let list = ScenarioList(all.iter().map(|s| s.name()).collect());
    let mine = match shard {
        Some(s) => s.deal(all),
        None => all,
    };
    Ok((mine, list))
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
    let (mut f, _) = crate::files::open_regular(path, "input file")
        .with_context(|| format!("hashing {}", path.display()))?;
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
/// weights. `python -m module` planners name no file. Both external kinds: `cmd:` and `resident:`.
pub fn planner_files(planner: &str) -> Vec<PathBuf> {
    let Some(cmd) = planner
        .strip_prefix("cmd:")
        .or_else(|| planner.strip_prefix("resident:"))
    else {
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
    list: &ScenarioList,
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
        o.insert(LIST_KEY.into(), json!(list.0));
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
    let text = crate::files::read_regular_string(path, "file", crate::files::JSON_LIMIT)?;
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
pub fn prepare_out(out: &Path, config: &Value, resume: bool) -> Result<BatchOut> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    // one writer per folder: the lock is taken before anything there is read or written
    let lock = lock_out(out)?;
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
    Ok(BatchOut {
        dir: out.to_path_buf(),
        resume,
        fingerprint: config_fingerprint(config),
        _lock: lock,
    })
}

/// An output folder prepared for a batch ([`prepare_out`]): held for the batch's whole run (its lock is
/// released when it is dropped, or by the system when the process dies).
pub struct BatchOut {
    pub dir: PathBuf,
    pub resume: bool,
    /// [`config_fingerprint`] of the folder's configuration, written into every scenario record.
    pub fingerprint: String,
    _lock: OutLock,
}

/// The lock file of an output folder ([`lock_out`]).
pub const LOCK_FILE: &str = ".b2dr-lock";

/// The lock on an output folder: an exclusive `flock` on `<out>/.b2dr-lock`, which holds who took it (pid,
/// host, start time, command line). Dropping it empties the file and closes it (the system releases the lock);
/// a process killed holding it leaves the file full but the lock free, which the next run detects as stale.
pub struct OutLock {
    file: std::fs::File,
}

impl Drop for OutLock {
    fn drop(&mut self) {
        // an empty file marks a clean release; the lock itself goes with the handle
        let _ = self.file.set_len(0);
    }
}

/// Takes the lock of `out` (issue #36, item 1: one writer per output folder). A folder another live run holds
/// is refused, naming the holder; a lock left by a killed run (the system released it, its file still names
/// the run) is reported as stale and taken over. On a filesystem without `flock` the run goes on unlocked,
/// with a warning.
pub fn lock_out(out: &Path) -> Result<OutLock> {
    use std::io::{Read, Seek, Write};
    let path = out.join(LOCK_FILE);
    let mut file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .with_context(|| format!("--out {}: creating the lock file", out.display()))?;
    ensure!(
        file.metadata().map(|m| m.is_file()).unwrap_or(false),
        "--out {}: {} is not a regular file",
        out.display(),
        path.display()
    );
    let mut holder = String::new();
    let _ = file.read_to_string(&mut holder);
    let holder = holder.trim().to_string();
    #[cfg(unix)]
    {
        use std::os::unix::io::AsRawFd;
        // SAFETY: flock on a file descriptor this function owns; no memory is passed
        let r = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if r != 0 {
            let err = std::io::Error::last_os_error();
            if err.raw_os_error() == Some(libc::EWOULDBLOCK) {
                bail!(
                    "--out {} is in use by another b2dr run ({}); one run writes a folder at a time: wait for it \
                     to end, or give another --out (the lock: {})",
                    out.display(),
                    describe_holder(&holder),
                    path.display()
                );
            }
            eprintln!(
                "warning: --out {}: cannot lock {} ({err}); the filesystem has no flock: nothing stops a second \
                 run on this folder",
                out.display(),
                path.display()
            );
        }
    }
    if !holder.is_empty() {
        eprintln!(
            "note: --out {}: a stale lock ({}) was found: that run ended without releasing it (killed?); taken \
             over",
            out.display(),
            describe_holder(&holder)
        );
    }
    let me = json!({
        "pid": std::process::id(),
        "host": std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_default(),
        "since_unix_s": std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0),
        "command": std::env::args().collect::<Vec<_>>().join(" "),
    });
    file.set_len(0)
        .and_then(|_| file.rewind())
        .and_then(|_| file.write_all(me.to_string().as_bytes()))
        .and_then(|_| file.flush())
        .with_context(|| format!("--out {}: writing the lock file", out.display()))?;
    Ok(OutLock { file })
}

/// "pid P on host H since T: COMMAND" from a lock file's text (or the text itself when it is not ours).
fn describe_holder(text: &str) -> String {
    let Ok(v) = serde_json::from_str::<Value>(text) else {
        return if text.is_empty() {
            "holder unknown".into()
        } else {
            format!("holder {:?}", text.chars().take(200).collect::<String>())
        };
    };
    format!(
        "pid {} on host {} since unix time {} s: {}",
        v["pid"],
        v["host"].as_str().unwrap_or("?"),
        v["since_unix_s"],
        v["command"].as_str().unwrap_or("?")
    )
}

/// Key of a scenario record (its `metrics.json`) holding [`config_fingerprint`] of the configuration that made
/// it.
pub const FINGERPRINT_KEY: &str = "config_fingerprint";

/// The fingerprint of what decides a scenario's result in a batch configuration: the configuration without
/// the shard and without the scenario files' entries of `input_files` (those differ between the shards of one
/// batch), so with the planner, renderer, model and their files' fingerprints: XXH3-128 of its JSON text, hex.
pub fn config_fingerprint(config: &Value) -> String {
    let mut c = config.clone();
    if let Some(o) = c.as_object_mut() {
        o.remove("shard");
        if let Some(Value::Object(inputs)) = o.get_mut(INPUTS_KEY) {
            inputs.retain(|_, v| v["role"] != "scenario");
        }
    }
    format!(
        "{:032x}",
        xxhash_rust::xxh3::xxh3_128(c.to_string().as_bytes())
    )
}

/// Checks one scenario record (a scenario's `metrics.json`, an entry of a summary's `scenarios`) before it is
/// trusted (issue #36): made by the configuration of `fingerprint`, a scenario name, the score and every metric
/// a finite number in [0, 1] (a failed scenario may carry no metrics, and then scores 0), timings finite and
/// non-negative. `Err` names the field.
pub fn check_record(v: &Value, fingerprint: &str) -> std::result::Result<(), String> {
    let unit = |x: &Value, field: &str| -> std::result::Result<f64, String> {
        match x.as_f64() {
            Some(f) if f.is_finite() && (0.0..=1.0).contains(&f) => Ok(f),
            _ => Err(format!("field `{field}` is {x}, not a number in [0, 1]")),
        }
    };
    let o = v.as_object().ok_or("not a JSON object")?;
    if !matches!(o.get("scenario"), Some(Value::String(_))) {
        return Err("field `scenario` is not a name".into());
    }
    match o.get(FINGERPRINT_KEY).and_then(Value::as_str) {
        Some(f) if f == fingerprint => {}
        Some(f) => {
            return Err(format!(
                "field `{FINGERPRINT_KEY}` is {f}, but this folder's configuration is {fingerprint}: the record \
                 was made by another configuration (planner, renderer, model or their files)"
            ))
        }
        None => {
            return Err(format!(
                "no field `{FINGERPRINT_KEY}`: the record was not finished by a run of this configuration"
            ))
        }
    }
    let score = unit(o.get("score").unwrap_or(&Value::Null), "score")?;
    match o.get("metrics") {
        Some(Value::Object(m)) => {
            for k in METRICS {
                unit(m.get(k).unwrap_or(&Value::Null), &format!("metrics.{k}"))?;
            }
        }
        None | Some(Value::Null) => {
            let failed = !o.get("failure").unwrap_or(&Value::Null).is_null()
                || !o.get("metrics_error").unwrap_or(&Value::Null).is_null();
            if !failed || score != 0.0 {
                return Err(
                    "field `metrics` is missing, but the record names no failure (or scores above 0)".into(),
                );
            }
        }
        Some(x) => return Err(format!("field `metrics` is {x}, not an object")),
    }
    let time = |x: &Value, field: &str| -> std::result::Result<(), String> {
        match x.as_f64() {
            Some(f) if f.is_finite() && f >= 0.0 => Ok(()),
            _ => Err(format!(
                "field `{field}` is {x}, not a finite non-negative time"
            )),
        }
    };
    if let Some(w) = o.get("wall_ms") {
        time(w, "wall_ms")?;
    }
    match o.get("timing_ms") {
        None | Some(Value::Null) => {}
        Some(Value::Object(t)) => {
            for (k, x) in t {
                time(x, &format!("timing_ms.{k}"))?;
            }
        }
        Some(x) => return Err(format!("field `timing_ms` is {x}, not an object")),
    }
    Ok(())
}

/// Checks a summary's totals (CLS, metric means, timing sums) are finite: a sum of finite timings can still
/// overflow. `Err` names the field.
fn check_totals(summary: &Value) -> std::result::Result<(), String> {
    let finite = |x: &Value| x.as_f64().is_some_and(f64::is_finite);
    if !finite(&summary["cls"]) {
        return Err(format!("`cls` is {}", summary["cls"]));
    }
    for (group, obj) in [
        ("metric_means", &summary["metric_means"]),
        ("timing_ms", &summary["timing_ms"]),
    ] {
        for (k, x) in obj.as_object().into_iter().flatten() {
            if !finite(x) {
                return Err(format!("`{group}.{k}` is {x}"));
            }
        }
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
    batch: &BatchOut,
    sources: &[Source],
    mut run_one: impl FnMut(usize, &Source, &Path) -> Result<Value>,
    mut report: impl FnMut(&str, &Value),
) -> Result<Vec<Value>> {
    let mut results = Vec::with_capacity(sources.len());
    for (i, src) in sources.iter().enumerate() {
        let name = src.name();
        let dir = batch.dir.join(folder_name(&name));
        let done = dir.join("metrics.json");
        // --resume re-checks a finished record instead of trusting it (issue #36): one of another
        // configuration, another scenario, or with a value out of range is rerun, and named
        let reuse = if batch.resume && done.is_file() {
            let v = read_json(&done).context("delete it to rerun the scenario")?;
            let why = check_record(&v, &batch.fingerprint).and_then(|_| {
                if v["scenario"] == json!(name) {
                    Ok(())
                } else {
                    Err(format!("it is the record of scenario {}", v["scenario"]))
                }
            });
            match why {
                Ok(()) => Some(v),
                Err(why) => {
                    eprintln!(
                        "--resume: {}: {why}; the scenario {name} runs again",
                        done.display()
                    );
                    None
                }
            }
        } else {
            None
        };
        let v = match reuse {
            Some(v) => v,
            None => {
                let mut v = run_one(i, src, &dir).unwrap_or_else(
                    |e| json!({ "scenario": name, "failure": format!("{e:#}"), "score": 0.0 }),
                );
                // written here, once, last: a record carries its configuration's fingerprint
                if let Some(o) = v.as_object_mut() {
                    o.insert(FINGERPRINT_KEY.into(), json!(batch.fingerprint));
                }
                std::fs::create_dir_all(&dir).ok();
                write_atomic(&done, serde_json::to_string_pretty(&v)?.as_bytes())?;
                v
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
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let _lock = lock_out(out)?;
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
        check_shard(d, &cfg, shard, &summary, sc)?;
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
    check_totals(&summary).map_err(|why| {
        anyhow::anyhow!(
            "merge: the merged summary's {why}: not a number b2dr writes; nothing was written"
        )
    })?;
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

/// Verifies what one shard folder holds before it is merged (issue #36, item 2): its scenarios are exactly those
/// its configuration's scenario list and shard index deal it (nothing dropped, nothing foreign), each record
/// passes [`check_record`] against the shard's configuration, and its own CLS and failure count are those of
/// its records. Errors name the shard folder, the scenario and the field.
fn check_shard(d: &Path, cfg: &Value, shard: Shard, summary: &Value, sc: &[Value]) -> Result<()> {
    let at = format!("merge: {} (shard {shard})", d.display());
    let list: Vec<String> = match cfg.get(LIST_KEY) {
        Some(Value::Array(a)) => a
            .iter()
            .map(|x| x.as_str().map(str::to_string))
            .collect::<Option<_>>()
            .with_context(|| format!("{at}: config.json's `{LIST_KEY}` holds a non-name"))?,
        _ => bail!(
            "{at}: config.json has no `{LIST_KEY}` (written by an older b2dr), so which scenarios the shard \
             must hold cannot be checked; rerun the shard"
        ),
    };
    let want: std::collections::BTreeSet<String> =
        shard.deal(list).iter().map(|n| folder_name(n)).collect();
    let fp = config_fingerprint(cfg);
    let mut got = std::collections::BTreeSet::new();
    for v in sc {
        let name = v["scenario"].as_str().unwrap_or("?");
        check_record(v, &fp).map_err(|why| anyhow::anyhow!("{at}: scenario {name}: {why}"))?;
        let f = folder_name(name);
        ensure!(
            want.contains(&f),
            "{at}: scenario {name} is not one of the shard's scenarios (its configuration's `{LIST_KEY}` dealt \
             {shard} does not name it): a foreign result"
        );
        got.insert(f);
    }
    if let Some(m) = want.iter().find(|n| !got.contains(*n)) {
        bail!(
            "{at}: scenario {m} is missing from its metrics.json ({} of {} scenarios there): a dropped result; \
             rerun the shard with --resume",
            got.len(),
            want.len()
        );
    }
    let own = summarize(Map::new(), sc.to_vec());
    for k in ["cls", "failures"] {
        ensure!(
            summary[k] == own[k],
            "{at}: metrics.json's `{k}` is {}, but its scenarios give {}: the summary does not match its records",
            summary[k],
            own[k]
        );
    }
    Ok(())
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
        std::fs::write(
            d.join("metrics.json"),
            r#"{"scenarios": [], "cls": 0.0, "failures": 0}"#,
        )
        .unwrap();
        for (shard, needle) in [
            (json!({"index": 0, "count": 0}), "0 <= K < N"),
            (json!({"index": 5, "count": 2}), "0 <= K < N"),
            (
                json!({"index": 0, "count": 1_000_000_000_000_000_000u64}),
                "10/1000000000000000000 and 999999999999999989 more missing",
            ),
        ] {
            let cfg = json!({"command": "sim", "shard": shard, "scenario_list": []});
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
