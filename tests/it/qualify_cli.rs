//! The station tools without the service: `crestscan station plan` for a camera and lens, and
//! `crestscan qualify` over a master's repositioned runs, whose result `inspect --qualification`
//! applies where the bundle matches and refuses, naming the mismatch, where it does not.

use serde_json::Value;
use std::path::Path;
use std::process::Command;

fn crestscan(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_crestscan")).args(args).output().unwrap()
}

fn text(out: &std::process::Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

#[test]
fn station_plan_states_the_presets_station_and_refuses_a_bad_sensor() {
    // The presets' camera: 50 mm f/1.4 at 220 mm on 12 µm pixels, 864×320.
    let out = crestscan(&[
        "station",
        "plan",
        "--connection",
        "BC 4-1/2",
        "--sensor",
        "864x320",
        "--pixel-um",
        "12",
        "--lens-mm",
        "50",
        "--f-number",
        "1.4",
        "--distance-mm",
        "220",
    ]);
    let printed = text(&out);
    assert!(out.status.success(), "{printed}");
    assert!(printed.contains("object pixel      40.8 µm"), "{printed}");
    assert!(printed.contains("rows              1 "), "{printed}");
    assert!(printed.contains("class             standard"), "{printed}");
    let bad = crestscan(&[
        "station",
        "plan",
        "--connection",
        "BC 4-1/2",
        "--sensor",
        "864",
        "--pixel-um",
        "12",
        "--lens-mm",
        "50",
        "--f-number",
        "1.4",
        "--distance-mm",
        "220",
    ]);
    assert!(!bad.status.success());
    assert!(text(&bad).contains("--sensor \"864\""), "{}", text(&bad));
}

#[test]
fn qualify_writes_what_inspect_applies_at_that_station_only() {
    let dir = tempfile::tempdir().unwrap();
    let (masters, certificate) = (dir.path().join("masters"), dir.path().join("certificate.json"));
    let path = |p: &Path| p.to_str().unwrap().to_string();
    for placement in 101..=110 {
        let out = crestscan(&[
            "simulate",
            "--preset",
            "ci-reject",
            "--seed",
            "7",
            "--placement-seed",
            &placement.to_string(),
            "--certificate",
            &path(&certificate),
            "--out",
            &path(&masters.join(format!("run-{placement}"))),
            "--quiet",
        ]);
        assert!(out.status.success(), "{}", text(&out));
    }
    let qualification = dir.path().join("q.json");
    let out = crestscan(&[
        "qualify",
        "--station",
        "bench-1",
        "--master",
        &path(&masters),
        "--certificate",
        &path(&certificate),
        "--out",
        &path(&qualification),
    ]);
    assert!(out.status.success(), "{}", text(&out));
    let q: Value = serde_json::from_slice(&std::fs::read(&qualification).unwrap()).unwrap();
    assert_eq!(q["station"], "bench-1");
    assert_eq!(q["masters"][0]["runs"], 10);
    assert!(q["uncertainty"]["u_p_um"].as_f64().unwrap() > 0.0);
    // The held-out error after the chosen model is not above the error without one.
    assert!(q["rms_after_um"].as_f64().unwrap() <= q["rms_before_um"].as_f64().unwrap() + 1e-9, "{q}");

    // Another part of the design at the same station: applied.
    let part = dir.path().join("part");
    assert!(
        crestscan(&[
            "simulate",
            "--preset",
            "ci-reject",
            "--seed",
            "8",
            "--placement-seed",
            "208",
            "--out",
            &path(&part),
            "--quiet"
        ])
        .status
        .success()
    );
    let out = crestscan(&["inspect", &path(&part), "--qualification", &path(&qualification), "--json", "--quiet"]);
    assert!(out.status.success(), "{}", text(&out));
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["qualification"]["applied"], true, "{}", report["qualification"]);
    assert_eq!(report["station"]["qualified_by"], q["study"]);
    // The ci bundle: the same optics and views, another connection: refused, naming it.
    let out = crestscan(&[
        "inspect",
        crate::common::ci_bundle().to_str().unwrap(),
        "--qualification",
        &path(&qualification),
        "--json",
        "--quiet",
    ]);
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    let refused = report["qualification"]["refused"].as_str().unwrap();
    assert!(refused.contains("covered LC 4-1/2 only") && refused.contains("BC 4-1/2"), "{refused}");
    assert_eq!(report["decision"], "indeterminate");
}
