//! Compiles `proto/socialflow/v1/*.proto` with the vendored `protoc`, so a fresh machine needs
//! no system protobuf compiler.
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let protoc = protoc_bin_vendored::protoc_bin_path()?;
    // SAFETY: build scripts are single-threaded; nothing else reads the environment concurrently.
    unsafe { std::env::set_var("PROTOC", protoc) };
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../proto");
    let file = root.join("socialflow/v1/socialflow.proto");
    println!("cargo:rerun-if-changed={}", file.display());
    tonic_prost_build::configure().build_client(true).build_server(true).compile_protos(&[file], &[root])?;
    Ok(())
}
