//! `instpol cli-spec` (hidden): every command's arguments and the kind of value each takes,
//! read from the clap definition itself, so that a test can enumerate the commands and their
//! inputs instead of listing them by hand (crates/cli/tests/hostile.rs).

use anyhow::Result;
use clap::CommandFactory;

/// Print every command and its arguments as JSON: for each command its name and, per argument,
/// its id, its long flag (none for a positional one), and the kind of value it takes: `number`
/// (a float or integer), `path` (a file or folder), `flag` (no value), `choice` (one of its
/// listed values) or `text` (anything else, parsed by the command: `8` or `2.5fwhm`, `12,20`).
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
    multiple: bool,
    required: bool,
    choices: Vec<String>,
}

#[derive(serde::Serialize)]
struct CommandSpec {
    name: String,
    args: Vec<ArgSpec>,
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
                    multiple: a.get_num_args().is_some_and(|n| n.max_values() > 1)
                        || matches!(a.get_action(), clap::ArgAction::Append),
                    required: a.is_required_set(),
                    choices: a.get_possible_values().iter().map(|v| v.get_name().to_string()).collect(),
                })
                .collect(),
        })
        .collect();
    let text = serde_json::to_string_pretty(&spec)?;
    outln!("{text}");
    Ok(())
}
