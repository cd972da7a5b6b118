//! `instpol cli-spec` (hidden): every command's arguments and the kind of value each takes,
//! read from the clap definition itself, so that a test can enumerate the commands and their
//! inputs instead of listing them by hand (crates/cli/tests/it/hostile.rs).

use anyhow::Result;
use clap::CommandFactory;

/// Print every command and its arguments as JSON: for each command its name and, per argument,
/// its id, its long flag (none for a positional one), and the kind of value it takes: `number`
/// (a float or integer), `path` (a file or folder), `flag` (no value), `choice` (one of its
/// listed values) or `text` (anything else, parsed by the command: `8` or `2.5fwhm`, `12,20`);
/// its role: `output` for the arguments that name files the command writes
/// (`util::OUTPUT_ARGUMENTS`), `input` for every other path argument and for `--instrument`
/// (a file when it names one), none otherwise; and its help text (which states a number's unit).
/// A tool for tests and scripts; not shown in `instpol --help`.
///
/// Example: instpol cli-spec > commands.json
#[derive(clap::Args)]
pub struct Args {}

#[derive(serde::Serialize)]
struct ArgSpec {
    id: String,
    long: Option<String>,
    kind: &'static str,
    role: Option<&'static str>,
    multiple: bool,
    required: bool,
    choices: Vec<String>,
    help: String,
}

#[derive(serde::Serialize)]
struct CommandSpec {
    name: String,
    args: Vec<ArgSpec>,
}

/// Whether the argument names a file the command writes, one it reads, or neither (the same
/// division as `util::guard_arguments`, which guards the inputs against being written over).
fn role(a: &clap::Arg, kind: &str) -> Option<&'static str> {
    let id = a.get_id().as_str();
    if crate::util::OUTPUT_ARGUMENTS.contains(&id) {
        Some("output")
    } else if kind == "path" || id == "instrument" {
        Some("input")
    } else {
        None
    }
}

fn kind(a: &clap::Arg) -> &'static str {
    if crate::util::is_numeric_arg(a) {
        "number"
    } else if a.get_value_parser().type_id() == std::any::TypeId::of::<std::path::PathBuf>() {
        "path"
    } else if matches!(a.get_action(), clap::ArgAction::SetTrue | clap::ArgAction::SetFalse | clap::ArgAction::Count) {
        "flag"
    } else if !a.get_possible_values().is_empty() {
        "choice"
    } else {
        "text"
    }
}

pub fn run(_a: Args) -> Result<()> {
    let mut cli = crate::Cli::command();
    cli.build();
    let spec: Vec<CommandSpec> = cli
        .get_subcommands()
        .filter(|s| !s.is_hide_set() && s.get_name() != "help")
        .map(|s| CommandSpec {
            name: s.get_name().to_string(),
            args: s
                .get_arguments()
                .filter(|a| !matches!(a.get_action(), clap::ArgAction::Help | clap::ArgAction::Version))
                .map(|a| ArgSpec {
                    id: a.get_id().to_string(),
                    long: a.get_long().map(|l| format!("--{l}")),
                    kind: kind(a),
                    role: role(a, kind(a)),
                    multiple: a.get_num_args().is_some_and(|n| n.max_values() > 1)
                        || matches!(a.get_action(), clap::ArgAction::Append),
                    required: a.is_required_set(),
                    choices: a.get_possible_values().iter().map(|v| v.get_name().to_string()).collect(),
                    help: a.get_long_help().or(a.get_help()).map(|h| h.to_string()).unwrap_or_default(),
                })
                .collect(),
        })
        .collect();
    let text = serde_json::to_string_pretty(&spec)?;
    outln!("{text}");
    Ok(())
}
