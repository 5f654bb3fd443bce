use clap::Parser;
use viscoprobe_daemon::cli::{dispatch, Cli};

fn main() -> std::process::ExitCode {
    viscoprobe_daemon::tune_allocator();
    let cli = Cli::parse();
    match dispatch(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", viscoprobe_daemon::output::error_text(&e));
            std::process::ExitCode::FAILURE
        }
    }
}
