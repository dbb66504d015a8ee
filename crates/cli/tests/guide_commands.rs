//! Every shell command in the user guide (docs/guide) run as written, against the built
//! binary on simulated devices: each ```sh block of each page, in order, in a scratch folder
//! that holds the repository's files (so `crates/cli/examples/rig-sim.toml` is where the guide
//! says). Marks after `sh,` say how a block runs:
//! - `serve`: with `dioptra serve --config crates/cli/examples/rig-sim.toml` running (the guide
//!   says "with the daemon running"; it is started before the block and stopped after);
//! - `fails`: the block must exit non-zero (an error the guide shows);
//! - `hardware`: needs a real device, skipped; `system`: changes the machine (sudo, systemctl,
//!   installs), skipped; `build`: builds the project from source (CI's own steps run it),
//!   skipped.
//!
//! Python blocks find this checkout's client (`PYTHONPATH=clients/python`), as after the
//! guide's `pip install ./clients/python`; it needs numpy and websocket-client installed.
//!
//! Also: every page is in SUMMARY.md and every SUMMARY link names a page that exists (what
//! mdBook needs to build; CI builds the book with mdBook too).

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn guide() -> PathBuf {
    repo().join("docs/guide/src")
}

#[derive(Debug, PartialEq)]
struct Block {
    /// The page and the line its fence opens on.
    at: String,
    marks: Vec<String>,
    text: String,
}

/// The ```sh blocks of a page (any fence of three or more backticks; `sh` or `sh,MARK,...`).
fn sh_blocks(page: &str, text: &str) -> Vec<Block> {
    let mut out = Vec::new();
    let mut lines = text.lines().enumerate();
    while let Some((n, line)) = lines.next() {
        let trimmed = line.trim_start();
        let ticks = trimmed.chars().take_while(|&c| c == '`').count();
        if ticks < 3 {
            continue;
        }
        let fence = &trimmed[..ticks];
        let info = trimmed[ticks..].trim();
        let mut body = String::new();
        for (_, l) in lines.by_ref() {
            if l.trim_start().starts_with(fence) && l.trim()[ticks..].trim().is_empty() {
                break;
            }
            body.push_str(l);
            body.push('\n');
        }
        let mut words = info.split(',').map(str::trim);
        if words.next() == Some("sh") {
            out.push(Block {
                at: format!("{page}:{}", n + 1),
                marks: words.map(str::to_string).collect(),
                text: body,
            });
        }
    }
    out
}

/// The guide's pages, in SUMMARY.md's order, and the links SUMMARY names that do not exist.
fn pages() -> (Vec<PathBuf>, Vec<String>) {
    let summary = std::fs::read_to_string(guide().join("SUMMARY.md")).unwrap();
    let mut pages = Vec::new();
    let mut broken = Vec::new();
    for link in summary.split("](").skip(1) {
        let target = link.split(')').next().unwrap();
        if target.is_empty() {
            continue;
        }
        let path = guide().join(target);
        if path.is_file() {
            pages.push(path);
        } else {
            broken.push(target.to_string());
        }
    }
    (pages, broken)
}

/// A process group that is killed whole when dropped (a block's background jobs with it).
struct Group(Child);

impl Drop for Group {
    fn drop(&mut self) {
        // SAFETY: kill(2) on the group this test made the child lead.
        unsafe { libc::kill(-(self.0.id() as i32), libc::SIGKILL) };
        let _ = self.0.wait();
    }
}

/// A scratch folder holding the repository's top-level entries as links (not target/ or
/// .git): commands see the files the guide names, and what they write lands here.
fn workdir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(repo()).unwrap() {
        let entry = entry.unwrap();
        let name = entry.file_name();
        if name == "target" || name == ".git" {
            continue;
        }
        std::os::unix::fs::symlink(entry.path(), dir.path().join(&name)).unwrap();
    }
    dir
}

fn path_with_binary() -> std::ffi::OsString {
    let bin = Path::new(env!("CARGO_BIN_EXE_dioptra")).parent().unwrap();
    let mut paths = vec![bin.to_path_buf()];
    paths.extend(std::env::split_paths(
        &std::env::var_os("PATH").unwrap_or_default(),
    ));
    std::env::join_paths(paths).unwrap()
}

/// Starts the example rig's daemon in `dir`; returns once its API answers.
fn serve(dir: &Path) -> Group {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_dioptra"));
    cmd.args(["serve", "--config", "crates/cli/examples/rig-sim.toml"])
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    std::os::unix::process::CommandExt::process_group(&mut cmd, 0);
    let mut child = cmd.spawn().unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let group = Group(child);
    let mut seen = String::new();
    loop {
        let mut line = String::new();
        if stderr.read_line(&mut line).unwrap() == 0 {
            panic!(
                "the example rig's daemon ended before it listened (is port 7420 taken?): {seen}"
            );
        }
        if line.starts_with("dioptra serve: API on") {
            break;
        }
        seen += &line;
    }
    // Keep reading its stderr so that it never blocks on a full pipe.
    std::thread::spawn(move || for _ in stderr.lines() {});
    group
}

/// Runs one block with bash (-e, pipefail) in `dir`: (exit code, output), or an error when it
/// ran past `limit` (then killed with its background jobs).
fn run(block: &Block, dir: &Path, limit: Duration) -> Result<(i32, String), String> {
    let out = dir.join(".block-output");
    let file = std::fs::File::create(&out).unwrap();
    let mut cmd = Command::new("bash");
    cmd.args(["-e", "-o", "pipefail", "-c", &block.text])
        .current_dir(dir)
        .env("PATH", path_with_binary())
        // The Python client as `pip install ./clients/python` installs it: this checkout's.
        .env("PYTHONPATH", repo().join("clients/python"))
        .stdin(Stdio::null())
        .stdout(file.try_clone().unwrap())
        .stderr(file);
    std::os::unix::process::CommandExt::process_group(&mut cmd, 0);
    let mut group = Group(cmd.spawn().unwrap());
    let until = Instant::now() + limit;
    let code = loop {
        if let Some(status) = group.0.try_wait().unwrap() {
            break status.code().unwrap_or(-1);
        }
        if Instant::now() > until {
            drop(group);
            return Err(format!(
                "ran past {limit:?}: {}",
                std::fs::read_to_string(&out).unwrap_or_default()
            ));
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    drop(group);
    Ok((code, std::fs::read_to_string(&out).unwrap_or_default()))
}

#[test]
fn the_block_extractor_reads_marks_and_skips_other_languages() {
    let text = "# A\n```sh\ndioptra devices\n```\n```toml\nmode = 1\n```\n````sh,serve,fails\ncurl x\n```\nstill\n````\n";
    let blocks = sh_blocks("a.md", text);
    assert_eq!(
        blocks,
        [
            Block {
                at: "a.md:2".into(),
                marks: vec![],
                text: "dioptra devices\n".into()
            },
            Block {
                at: "a.md:8".into(),
                marks: vec!["serve".into(), "fails".into()],
                text: "curl x\n```\nstill\n".into()
            },
        ]
    );
}

#[test]
fn every_page_is_in_the_summary_and_every_summary_link_resolves() {
    let (pages, broken) = pages();
    assert!(
        broken.is_empty(),
        "SUMMARY.md links to missing pages: {broken:?}"
    );
    let mut unlisted = Vec::new();
    let mut stack = vec![guide()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "md")
                && p.file_name().unwrap() != "SUMMARY.md"
                && !pages.contains(&p)
            {
                unlisted.push(p);
            }
        }
    }
    assert!(unlisted.is_empty(), "pages not in SUMMARY.md: {unlisted:?}");
}

#[test]
fn every_shell_command_in_the_guide_runs_as_written() {
    let (pages, _) = pages();
    let dir = workdir();
    let skip = ["hardware", "system", "build"];
    let (mut ran, mut skipped, mut failed) = (0, Vec::new(), Vec::new());
    for page in &pages {
        let name = page.strip_prefix(guide()).unwrap().display().to_string();
        let text = std::fs::read_to_string(page).unwrap();
        for block in sh_blocks(&name, &text) {
            if let Some(m) = block.marks.iter().find(|m| skip.contains(&m.as_str())) {
                skipped.push(format!("{} ({m})", block.at));
                continue;
            }
            let unknown: Vec<&String> = block
                .marks
                .iter()
                .filter(|m| !["serve", "fails"].contains(&m.as_str()))
                .collect();
            assert!(
                unknown.is_empty(),
                "{}: unknown marks {unknown:?}",
                block.at
            );
            let daemon = block
                .marks
                .iter()
                .any(|m| m == "serve")
                .then(|| serve(dir.path()));
            let expect_failure = block.marks.iter().any(|m| m == "fails");
            eprintln!("{}: running", block.at);
            match run(&block, dir.path(), Duration::from_secs(300)) {
                Err(e) => failed.push(format!("{}: {e}\n{}", block.at, block.text)),
                Ok((code, out)) if (code == 0) == expect_failure => failed.push(format!(
                    "{}: exit {code} (expected {})\n{}--- output:\n{out}",
                    block.at,
                    if expect_failure { "a failure" } else { "0" },
                    block.text
                )),
                Ok(_) => ran += 1,
            }
            drop(daemon);
        }
    }
    eprintln!(
        "guide: {ran} blocks ran, {} skipped: {skipped:?}",
        skipped.len()
    );
    assert!(
        failed.is_empty(),
        "{} blocks failed:\n{}",
        failed.len(),
        failed.join("\n\n")
    );
    // The guide has commands in every chapter: an extractor that finds none is broken.
    assert!(ran >= 20, "only {ran} blocks ran");
}

#[test]
fn every_relative_link_in_the_guide_names_a_file_that_exists() {
    let (pages, _) = pages();
    let mut broken = Vec::new();
    for page in &pages {
        let text = std::fs::read_to_string(page).unwrap();
        let mut in_code = false;
        for (n, line) in text.lines().enumerate() {
            if line.trim_start().starts_with("```") {
                in_code = !in_code;
            }
            if in_code {
                continue;
            }
            for link in line.split("](").skip(1) {
                let Some(target) = link.split(')').next() else {
                    continue;
                };
                let file = target.split('#').next().unwrap();
                if file.is_empty() || file.contains("://") || file.starts_with("mailto:") {
                    continue;
                }
                if !page.parent().unwrap().join(file).exists() {
                    broken.push(format!(
                        "{}:{}: {target}",
                        page.strip_prefix(guide()).unwrap().display(),
                        n + 1
                    ));
                }
            }
        }
    }
    assert!(broken.is_empty(), "links to missing files: {broken:#?}");
}
