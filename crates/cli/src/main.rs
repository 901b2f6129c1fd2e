//! The `salient` binary: the command line lives in the `salient_cli` library.

fn main() -> std::process::ExitCode {
    salient_cli::main()
}
