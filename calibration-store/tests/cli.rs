//! The `store` subcommands, parsed as a binary mounts them and run against a store.

use clap::Parser;
use triax_calibration_store::cli::{run, CliError, StoreCommand};
use triax_calibration_store::Store;

use crate::util::{id, new_store, record};

/// A binary that mounts the shared subcommand, as `triax-gateway store …` does.
#[derive(Debug, Parser)]
struct App {
    #[command(subcommand)]
    command: Top,
}

#[derive(Debug, clap::Subcommand)]
enum Top {
    #[command(subcommand)]
    Store(StoreCommand),
}

fn parse(args: &[&str]) -> Result<StoreCommand, clap::Error> {
    App::try_parse_from(["app", "store"].iter().chain(args)).map(|app| match app.command {
        Top::Store(c) => c,
    })
}

fn output(store: &Store, args: &[&str]) -> (Result<(), CliError>, String) {
    let command = parse(args).unwrap();
    let mut out = Vec::new();
    let result = run(store, &command, &mut out);
    (result, String::from_utf8(out).unwrap())
}

#[test]
fn subcommands_parse() {
    assert_eq!(parse(&["list"]).unwrap(), StoreCommand::List);
    assert_eq!(
        parse(&["show", "s1", "--version", "2"]).unwrap(),
        StoreCommand::Show {
            sensor: id("s1"),
            version: Some(2),
            at: None
        }
    );
    match parse(&["show", "s1", "--at", "2026-03-01T12:00:00+01:00"]).unwrap() {
        StoreCommand::Show { at: Some(t), .. } => assert_eq!(t.unix_timestamp(), 1_772_362_800),
        other => panic!("{other:?}"),
    }
    assert!(parse(&["show", "s1", "--at", "yesterday"]).is_err());
    assert!(parse(&[
        "show",
        "s1",
        "--version",
        "2",
        "--at",
        "2026-03-01T12:00:00Z"
    ])
    .is_err());
    assert!(parse(&["show", "bad/id"]).is_err());
    assert!(matches!(
        parse(&["import", "/tmp/x"]).unwrap(),
        StoreCommand::Import { .. }
    ));
}

/// Times to the nanosecond (as `triax-lab fit` stamps them) are 30 characters, wider than the
/// columns' titles: every row's certificate still starts under its title.
#[test]
fn the_list_stays_a_table_with_nanosecond_times() {
    let (_dir, store) = new_store();
    store.put(&record("s1", 1)).unwrap().unwrap();
    let mut precise = record("sensor-long-name", 2);
    precise.issued_at += time::Duration::nanoseconds(123_456_789);
    precise.valid_from += time::Duration::nanoseconds(123_456_789);
    store.put(&precise).unwrap().unwrap();

    let (result, text) = output(&store, &["list"]);
    result.unwrap();
    let lines: Vec<&str> = text.lines().collect();
    let column = lines[0].find("CERTIFICATE").unwrap();
    assert_eq!(lines[1].find("SAMPLE-s1-1"), Some(column), "{text}");
    assert_eq!(
        lines[2].find("SAMPLE-sensor-long-name-2"),
        Some(column),
        "{text}"
    );
    assert!(lines[2].contains(".123456789Z"), "{text}");
    let until = lines[0].find("VALID UNTIL").unwrap();
    assert_eq!(lines[1].find(" -  ").map(|i| i + 1), Some(until), "{text}");
}

#[test]
fn list_show_history_export_import_print_for_people() {
    let (_dir, store) = new_store();
    for v in 1..=2 {
        store.put(&record("s1", v)).unwrap().unwrap();
    }
    store.put(&record("sensor-long-name", 4)).unwrap().unwrap();

    let (result, text) = output(&store, &["list"]);
    result.unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert!(lines[0].starts_with("SENSOR"), "{text}");
    assert!(
        lines[1].starts_with("s1 ") && lines[1].contains("SAMPLE-s1-2"),
        "{text}"
    );
    assert!(lines[1].contains("2026-01-01T00:00:00Z"), "{text}");
    assert!(lines[2].starts_with("sensor-long-name"), "{text}");
    assert_eq!(lines[3], "2 sensors");

    let (result, text) = output(&store, &["show", "s1"]);
    result.unwrap();
    let shown: triax_protocol::record::CalibrationRecord =
        triax_protocol::from_json(text.as_bytes()).unwrap();
    assert_eq!(shown, record("s1", 2));
    let (result, text) = output(&store, &["show", "s1", "--version", "1"]);
    result.unwrap();
    assert!(text.contains("\"version\": 1"), "{text}");
    let (result, text) = output(&store, &["show", "s1", "--at", "2026-06-01T00:00:00Z"]);
    result.unwrap();
    assert!(text.contains("\"version\": 2"), "{text}");
    let (result, _) = output(&store, &["show", "s1", "--at", "2025-06-01T00:00:00Z"]);
    let e = result.unwrap_err();
    assert!(
        e.to_string()
            .contains("no record in force at 2025-06-01T00:00:00Z"),
        "{e}"
    );
    let (result, _) = output(&store, &["show", "nope"]);
    assert!(matches!(result, Err(CliError::NotFound { .. })));

    let (result, text) = output(&store, &["history", "s1"]);
    result.unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 4, "{text}");
    assert!(!lines[1].contains("(current)"), "{text}");
    assert!(lines[2].ends_with("(current)"), "{text}");
    assert_eq!(lines[3], "2 versions");

    let backup = tempfile::tempdir().unwrap();
    let path = backup.path().to_str().unwrap();
    let (result, text) = output(&store, &["export", path]);
    result.unwrap();
    assert_eq!(text, format!("exported 3 records to {path}\n"));

    let (_dir2, other) = new_store();
    let (result, text) = output(&other, &["import", path]);
    result.unwrap();
    assert!(text.contains("stored     s1.v1.json"), "{text}");
    assert!(
        text.ends_with(&format!("imported 3 of 3 files from {path}\n")),
        "{text}"
    );

    std::fs::write(backup.path().join("broken.json"), b"{").unwrap();
    let (result, text) = output(&other, &["import", path]);
    assert!(
        text.contains("unchanged  s1.v2.json (already stored)"),
        "{text}"
    );
    assert!(text.contains("unreadable broken.json: "), "{text}");
    let e = result.unwrap_err();
    assert!(
        matches!(
            e,
            CliError::ImportIncomplete {
                refused: 1,
                files: 4
            }
        ),
        "{e:?}"
    );
}
