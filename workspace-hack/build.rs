// Empty: it makes cargo resolve and build the [build-dependencies] of Cargo.toml with the
// features listed there (build scripts and proc-macros resolve their features apart).
fn main() {}
