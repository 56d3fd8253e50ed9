//! `sim-harness`: rendezvous simulator command line.

fn main() {
    eprintln!("sim-harness: no command implemented yet");
    std::process::exit(2);
}
