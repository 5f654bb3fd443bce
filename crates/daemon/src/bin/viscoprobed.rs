use clap::Parser;
use viscoprobe_daemon::service::daemon::{main as daemon_main, Args};

fn main() -> std::process::ExitCode {
    viscoprobe_daemon::tune_allocator();
    daemon_main(Args::parse())
}
