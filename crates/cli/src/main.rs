//! The `socialflow` command; all logic lives in the `sf_cli` library.

fn main() -> std::process::ExitCode {
    sf_cli::main()
}
