//! The station tools without the service: `crestscan station plan` for a camera and lens,
//! `crestscan qualify` over a master's repositioned runs, whose result `inspect --qualification`
//! applies where the bundle matches and refuses, naming the mismatch, where it does not, and
//! `crestscan station check`, which charts later runs of the master and finds a refocus.

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
    assert!(printed.contains("U after a study   not studied by the benchmark"), "{printed}");
    // A coarse camera (36 µm pixels, f/0.5): the U the benchmark's coarse studies stated.
    let coarse = crestscan(&[
        "station",
        "plan",
        "--connection",
        "BC 4-1/2",
        "--sensor",
        "864x320",
        "--pixel-um",
        "36",
        "--lens-mm",
        "50",
        "--f-number",
        "0.5",
        "--distance-mm",
        "220",
    ]);
    let printed = text(&coarse);
    assert!(printed.contains("class             coarse"), "{printed}");
    assert!(printed.contains("U after a study   19.6–1520.5 µm (k = 2) at the 4 coarse stations"), "{printed}");
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

    // Drift control: the height bias is judged (rule 1 alone from 10 runs); the crest-cone radius,
    // which three views on one side place within a millimetre only, is shown but not judged.
    let limits = q["control"].as_array().unwrap();
    let bias = limits.iter().find(|l| l["statistic"] == "height_bias").unwrap();
    assert_eq!((bias["charted"].as_bool(), bias["rules"].clone()), (Some(true), serde_json::json!([1])), "{bias}");
    let radius = limits.iter().find(|l| l["statistic"] == "crest_cone_radius").unwrap();
    assert_eq!(radius["charted"], false, "{radius}");
    let render = |name: &str, placement: &str, drift: &str| {
        let run = dir.path().join(name);
        let out = crestscan(&[
            "simulate",
            "--preset",
            "ci-reject",
            "--seed",
            "7",
            "--placement-seed",
            placement,
            "--focus-drift-mm",
            drift,
            "--out",
            &path(&run),
            "--quiet",
        ]);
        assert!(out.status.success(), "{}", text(&out));
        path(&run)
    };
    let (clean, drifted) = (render("check-111", "111", "0"), render("check-121", "121", "0.2"));
    let chart = path(&dir.path().join("chart.json"));
    let (qualification_path, certificate_path) = (path(&qualification), path(&certificate));
    let check = |extra: &[&str]| {
        let mut args =
            vec!["station", "check", "--qualification", &qualification_path, "--certificate", &certificate_path];
        args.extend_from_slice(extra);
        crestscan(&args)
    };
    let out = check(&["--chart", &chart, &clean]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("check 1 ") && text(&out).contains("in control"), "{}", text(&out));
    let out = check(&["--history", &chart, &drifted]);
    assert_eq!(out.status.code(), Some(3), "{}", text(&out));
    assert!(text(&out).contains("check 2 ") && text(&out).contains("BROKE Western Electric rule 1"), "{}", text(&out));
    // Another study's chart is not continued.
    let mut other: Value = serde_json::from_slice(&std::fs::read(&chart).unwrap()).unwrap();
    other["study"] = "study-000000000000".into();
    std::fs::write(&chart, serde_json::to_vec(&other).unwrap()).unwrap();
    let out = check(&["--history", &chart, &clean]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out).contains("a new study starts a new chart"), "{}", text(&out));
}

/// The U `station plan` quotes per class is the benchmark page's: each station's row in
/// docs/benchmark.md's qualification table states the same U.
#[test]
fn the_plans_studied_u_is_the_benchmark_tables() {
    let page = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/benchmark.md")).unwrap();
    for (class, station, u) in crestscan::domain::station::QUALIFIED_U_UM {
        let row = page
            .lines()
            .find(|l| l.starts_with(&format!("| {station} |")))
            .unwrap_or_else(|| panic!("docs/benchmark.md has no row for {station}"));
        let study = row.split('|').nth(2).unwrap();
        let stated: Vec<f64> = study.split(',').filter_map(|c| c.trim().parse().ok()).collect();
        // The study cell: model, held-out RMS before → after, U, Cg min, Cgk min, %GRR.
        assert_eq!(stated.first(), Some(&u), "{station} ({}): the table says {study}", class.as_str());
    }
}

/// Two masters of the design (two parts, each placed ten times): the model is chosen holding a
/// master out, and u_w, the correction's spread between masters, is measured and in U.
#[test]
fn two_masters_measure_the_spread_between_them() {
    let dir = tempfile::tempdir().unwrap();
    let path = |p: &Path| p.to_str().unwrap().to_string();
    let mut args: Vec<String> = vec!["qualify".into(), "--station".into(), "bench-2".into()];
    for seed in [7u64, 9] {
        let (runs, certificate) =
            (dir.path().join(format!("master-{seed}")), dir.path().join(format!("cert-{seed}.json")));
        // The runs as `simulate --placement-seed` writes them, rendered once per test process (the
        // service's station tests study seed 7's too; the test above goes through the CLI), and
        // the certificate as `simulate --certificate` writes it: 2 µm (k = 2), the last run's truth.
        let mut last = None;
        for placement in 101..=110 {
            let render = crate::common::placed("ci-reject", None, seed, placement, 0.0);
            crate::common::copy_tree(render, &runs.join(format!("run-{placement}")), &|_| true);
            last = Some(render);
        }
        let cert = crestscan::sim::certificate(&crate::common::truth_of(last.unwrap()), 0.002, seed);
        std::fs::write(&certificate, serde_json::to_vec_pretty(&cert).unwrap()).unwrap();
        args.extend(["--master".into(), path(&runs), "--certificate".into(), path(&certificate)]);
    }
    let qualification = dir.path().join("q.json");
    args.extend(["--out".into(), path(&qualification)]);
    let out = crestscan(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.status.success(), "{}", text(&out));
    let q: Value = serde_json::from_slice(&std::fs::read(&qualification).unwrap()).unwrap();
    assert_eq!(q["masters"].as_array().unwrap().len(), 2);
    assert_eq!(q["selection"]["method"], "leave_one_master_out");
    let u = &q["uncertainty"];
    assert_eq!(u["u_w_measured"], true, "{u}");
    let component = |k: &str| u[k].as_f64().unwrap();
    assert!(component("u_w_um") > 0.0, "{u}");
    let combined = ["u_cal_um", "u_p_um", "u_b_um", "u_w_um"].iter().map(|k| component(k).powi(2)).sum::<f64>().sqrt();
    assert!((component("combined_um") - combined).abs() < 1e-9, "{u}");
    // Each master has its own control limits.
    let charted: std::collections::BTreeSet<&str> =
        q["control"].as_array().unwrap().iter().map(|l| l["master"].as_str().unwrap()).collect();
    assert_eq!(charted.len(), 2, "{}", q["control"]);
}
