//! `msth inspect` as a separate process: on a trained and exported model (the codec fixture,
//! `tests/fixtures/v1.msth`), on files of the bad corpus (non-zero exit, the message names the
//! violation), and over HTTP against a real `msth serve` on loopback, where it reads only the
//! prefix unless `--validate` asks for every section.

use std::path::PathBuf;
use std::process::Command;

mod support;

fn repo(path: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(path)
}

/// Runs `msth ARGS`; returns (success, stdout, stderr).
fn msth(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_msth"))
        .args(args)
        .output()
        .expect("msth runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into(),
        String::from_utf8_lossy(&out.stderr).into(),
    )
}

fn inspect_json(args: &[&str]) -> serde_json::Value {
    let mut a = vec!["inspect", "--json"];
    a.extend_from_slice(args);
    let (ok, out, err) = msth(&a);
    assert!(ok, "msth {a:?} failed: {err}");
    serde_json::from_str(&out).unwrap_or_else(|e| panic!("{e}: {out}"))
}

#[test]
fn inspect_describes_and_validates_an_exported_model() {
    let file = repo("tests/fixtures/v1.msth");
    let f = file.to_str().unwrap();
    let bytes = std::fs::read(&file).unwrap();
    let decoded = msth_codec::decode_all(&bytes).unwrap();
    let v = inspect_json(&[f]);
    assert_eq!(v["valid"], true);
    assert_eq!(v["validated"], true);
    assert_eq!(v["file_bytes"], bytes.len() as u64);
    assert_eq!(v["header"]["version"], 1);
    let sections = v["sections"].as_array().unwrap();
    let chunks = decoded.metadata.chunks.len();
    assert_eq!(sections.len(), if chunks == 0 { 3 } else { 4 + chunks });
    // Section sizes add up to the file (prefix, sections, padding below 8 bytes each).
    let stored: u64 = sections
        .iter()
        .map(|s| s["stored_bytes"].as_u64().unwrap())
        .sum();
    let hs = v["header"]["header_size"].as_u64().unwrap();
    let n = sections.len() as u64;
    assert!(stored + hs <= bytes.len() as u64 && bytes.len() as u64 <= stored + hs + 8 * n);
    assert_eq!(sections[0]["kind"], "mlp");
    assert!(sections.iter().all(|s| s["ratio"].as_f64().unwrap() > 0.0));
    assert_eq!(v["chunks"].as_array().unwrap().len(), chunks);
    assert_eq!(v["param_count"], decoded.params.len() as u64);
    // The shares are computed from the decoded sections: within (0, 1].
    let share = v["h4_rows_stored_share"].as_f64().unwrap();
    assert!(share > 0.0 && share <= 1.0, "{share}");
    let dynamic = v["dynamic_voxels"]["share"].as_f64().unwrap();
    assert!(dynamic > 0.0 && dynamic <= 1.0, "{dynamic}");
    assert_eq!(
        v["cameras"].as_array().unwrap().len(),
        decoded.cameras.len()
    );
    // The text form says the same in lines.
    let (ok, text, _) = msth(&["inspect", f]);
    assert!(ok);
    println!("{text}");
    for needle in [
        "version 1",
        "valid",
        "sections",
        "chunk 0",
        "4D rows",
        "dynamic",
        "cameras",
    ] {
        assert!(text.contains(needle), "`{needle}` missing:\n{text}");
    }
}

/// Version 2 (issue #17): the occupancy section is listed and described; version 1 says it has
/// none.
#[test]
fn inspect_shows_the_occupancy_section() {
    let file = repo("tests/fixtures/v2.msth");
    let f = file.to_str().unwrap();
    let decoded = msth_codec::decode_all(&std::fs::read(&file).unwrap()).unwrap();
    let grid = decoded.occupancy.unwrap();
    let v = inspect_json(&[f]);
    assert_eq!(v["header"]["version"], 2);
    let sections = v["sections"].as_array().unwrap();
    assert_eq!(sections[3]["kind"], "occupancy");
    assert_eq!(v["occupancy"]["resolution"], grid.resolution);
    assert_eq!(v["occupancy"]["occupied_cells"], grid.occupied_cells());
    assert_eq!(v["occupancy"]["cells"], grid.cells());
    let (ok, text, _) = msth(&["inspect", f]);
    assert!(ok);
    println!("{text}");
    let line = format!(
        "occupancy   {}^3 cells, {} occupied",
        grid.resolution,
        grid.occupied_cells()
    );
    assert!(text.contains(&line), "`{line}` missing:\n{text}");
    let (ok, text, _) = msth(&["inspect", repo("tests/fixtures/v1.msth").to_str().unwrap()]);
    assert!(ok);
    assert!(
        text.contains("occupancy   none (a version-1 file"),
        "{text}"
    );
}

#[test]
fn inspect_exits_non_zero_with_the_first_violation() {
    for (file, needles) in [
        (
            "43_zstd_two_frames.msth",
            &["dynamic chunk 1", "zstd frame"][..],
        ),
        ("46_time_range_not_unit.msth", &["time_range", "[0, 1]"]),
        (
            "47_huge_camera.msth",
            &["cameras[0] width", "100000", "16384"],
        ),
        (
            "48_huge_sampler.msth",
            &["model.sampler.num_proposal_samples", "4096", "1024"],
        ),
        ("26_trailing_bytes.msth", &["trailing bytes"]),
        ("32_nonzero_padding.msth", &["padding"]),
        (
            "21_bad_section_checksum.msth",
            &["checksum", "static section"],
        ),
    ] {
        let p = repo("tests/bad").join(file);
        let (ok, _, err) = msth(&["inspect", p.to_str().unwrap()]);
        assert!(!ok, "{file}: accepted");
        println!("{file}: {}", err.trim());
        assert!(err.contains("not a valid .msth file"), "{file}: {err}");
        for n in needles {
            assert!(err.contains(n), "{file}: `{err}` should mention `{n}`");
        }
    }
}

#[test]
fn inspect_over_http_reads_the_prefix_unless_asked_to_validate() {
    let dir = tempfile::tempdir().unwrap();
    let good = std::fs::read(repo("tests/fixtures/v1.msth")).unwrap();
    // The fixture (137 KB) is well above the first request's 16 KiB.
    std::fs::write(dir.path().join("good.msth"), &good).unwrap();
    std::fs::copy(
        repo("tests/bad/43_zstd_two_frames.msth"),
        dir.path().join("two_frames.msth"),
    )
    .unwrap();
    let (_server, base) = support::serve(dir.path(), &[]);
    let url = format!("{base}/models/good.msth");
    let local = inspect_json(&[repo("tests/fixtures/v1.msth").to_str().unwrap()]);
    let v = inspect_json(&[&url]);
    assert_eq!(v["valid"], true);
    assert_eq!(v["validated"], false);
    assert_eq!(v["sections"], local["sections"]);
    assert_eq!(v["metadata"], local["metadata"]);
    assert!(v["h4_rows_stored_share"].is_null());
    let read = v["bytes_read"].as_u64().unwrap();
    let hs = v["header"]["header_size"].as_u64().unwrap();
    assert!(
        read >= hs && read <= hs.max(16 << 10),
        "read {read} bytes for a {hs}-byte prefix"
    );
    if good.len() > 16 << 10 {
        assert!(read < good.len() as u64, "read the whole file: {read}");
    }
    // --validate fetches and checks everything: the same report as the local file.
    let all = inspect_json(&[&url, "--validate"]);
    assert_eq!(all["validated"], true);
    assert_eq!(all["h4_rows_stored_share"], local["h4_rows_stored_share"]);
    assert_eq!(all["dynamic_voxels"], local["dynamic_voxels"]);
    assert!(all["bytes_read"].as_u64().unwrap() >= good.len() as u64);
    // A file whose fault is in a section: the prefix alone passes, --validate finds it.
    let bad = format!("{base}/models/two_frames.msth");
    let (ok, _, _) = msth(&["inspect", &bad]);
    assert!(ok, "the prefix of two_frames.msth is valid");
    let (ok, _, err) = msth(&["inspect", &bad, "--validate"]);
    assert!(!ok && err.contains("zstd frame"), "{err}");
}

#[test]
fn a_reader_that_closes_the_pipe_early_is_not_a_crash() {
    // The read end is closed before `msth` writes, so its first line already meets a broken
    // pipe (what `msth inspect FILE | head -1` does once head has its line).
    let (reader, writer) = std::io::pipe().expect("pipe");
    drop(reader);
    let file = repo("tests/fixtures/v1.msth");
    for args in [
        vec!["inspect", file.to_str().unwrap()],
        vec!["bench", "play", "--help"],
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_msth"))
            .args(&args)
            .stdout(writer.try_clone().expect("clone the pipe's write end"))
            .stderr(std::process::Stdio::piped())
            .output()
            .expect("msth runs");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.success() && !err.contains("panicked"),
            "msth {args:?} with a closed stdout: {:?}\n{err}",
            out.status
        );
    }
}
