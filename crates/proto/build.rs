//! Compiles proto/salient/v1 with protox (pure Rust), so the build needs no system `protoc`.

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../proto");
    let file = root.join("salient/v1/salient.proto");
    println!("cargo:rerun-if-changed={}", file.display());
    let fds = protox::compile([&file], [&root]).expect("proto/salient/v1/salient.proto compiles");
    tonic_prost_build::configure()
        // Relayed outcomes are shared by every worker's reply: `Bytes` clones by reference.
        .bytes(".salient.v1.Relay.outcomes")
        .compile_fds(fds)
        .expect("code generation from the descriptor set");
}
