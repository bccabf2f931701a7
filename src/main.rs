fn main() {
    std::process::exit(freefall::cli::run());
}
