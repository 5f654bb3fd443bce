use clap::Parser;
use viscoprobe_daemon::service::daemon::{main as daemon_main, Args};

fn main() -> std::process::ExitCode {
    daemon_main(Args::parse())
}
