//! The README's commands still parse (issue 49): every `crestscan SUBCOMMAND --flag …` its shell
//! blocks run names a subcommand the binary has, and each flag is one that subcommand's `--help`
//! lists.

/// (subcommand, flags) of each crestscan command line in the README's ```sh blocks.
fn readme_commands(readme: &str) -> Vec<(String, Vec<String>)> {
    let mut commands = Vec::new();
    let mut in_shell = false;
    for line in readme.lines() {
        if line.starts_with("```") {
            in_shell = line.trim() == "```sh";
            continue;
        }
        if !in_shell {
            continue;
        }
        let code = line.split(" #").next().unwrap_or(line);
        for part in code.split("&&") {
            let words: Vec<&str> = part.split_whitespace().collect();
            // `crestscan SUB …`, or `cargo run … -- SUB …`; not the shell function's definition.
            let start = words.iter().position(|w| *w == "crestscan" || *w == "--").map(|i| i + 1);
            let Some(sub) =
                start.and_then(|i| words.get(i)).filter(|w| w.chars().all(|c| c.is_ascii_lowercase() || c == '-'))
            else {
                continue;
            };
            let flags = words[start.unwrap() + 1..]
                .iter()
                .filter(|w| w.starts_with("--"))
                .map(|w| w.split('=').next().unwrap().to_string())
                .collect();
            commands.push((sub.to_string(), flags));
        }
    }
    commands
}

#[test]
fn the_readme_commands_name_real_subcommands_and_flags() {
    let readme = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).unwrap();
    let commands = readme_commands(&readme);
    let subcommands: std::collections::BTreeSet<&str> = commands.iter().map(|(s, _)| s.as_str()).collect();
    for expected in ["serve", "simulate", "inspect", "compare"] {
        assert!(subcommands.contains(expected), "the README's {expected} command was not read: {commands:?}");
    }
    for (sub, flags) in &commands {
        let help = std::process::Command::new(env!("CARGO_BIN_EXE_crestscan"))
            .args([sub.as_str(), "--help"])
            .output()
            .unwrap();
        assert!(help.status.success(), "`crestscan {sub} --help` failed: {}", String::from_utf8_lossy(&help.stderr));
        let text = String::from_utf8_lossy(&help.stdout);
        for flag in flags {
            assert!(
                text.contains(flag.as_str()),
                "the README runs `crestscan {sub} {flag}`, which its --help does not list"
            );
        }
    }
}

#[test]
fn the_reader_takes_both_spellings_and_skips_comments() {
    let text = "```sh\ncargo run --release --locked -- serve --bind x # --not-a-flag\ncrestscan simulate --preset ci --out=o\n```\n```text\ncrestscan ignored --x\n```\n";
    assert_eq!(
        readme_commands(text),
        [
            ("serve".to_string(), vec!["--bind".to_string()]),
            ("simulate".to_string(), vec!["--preset".to_string(), "--out".to_string()])
        ]
    );
}

/// The commit-msg hook CONTRIBUTING.md asks for refuses a 73-character subject and takes 72.
#[test]
fn commit_hook_refuses_long_subjects() {
    let hook = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(".githooks/commit-msg");
    let dir = tempfile::tempdir().unwrap();
    let run = |subject: &str| {
        let file = dir.path().join("MSG");
        std::fs::write(&file, format!("{subject}\n\nbody line\n# a comment\n")).unwrap();
        std::process::Command::new("sh").arg(&hook).arg(&file).output().unwrap()
    };
    let ok = run(&"a".repeat(72));
    assert!(ok.status.success(), "{}", String::from_utf8_lossy(&ok.stderr));
    let long = run(&"a".repeat(73));
    assert!(!long.status.success());
    assert!(String::from_utf8_lossy(&long.stderr).contains("73 characters"));
    let empty = run("");
    assert!(!empty.status.success());
}
