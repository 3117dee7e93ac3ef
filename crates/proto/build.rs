//! Compiles `proto/socialflow/v1/*.proto` with the vendored `protoc`, so a fresh machine needs
//! no system protobuf compiler.
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let protoc = protoc_bin_vendored::protoc_bin_path()?;
    // SAFETY: build scripts are single-threaded; nothing else reads the environment concurrently.
    unsafe { std::env::set_var("PROTOC", protoc) };
    // The directory cargo runs this script for, read at run time: a compile-time `env!` would
    // bake in the checkout the script was first built from, and checkouts share a target dir.
    let manifest = std::env::var("CARGO_MANIFEST_DIR")?;
    let root = std::path::Path::new(&manifest).join("../../proto");
    let file = root.join("socialflow/v1/socialflow.proto");
    println!("cargo:rerun-if-changed={}", file.display());
    // The descriptor set serves gRPC reflection (`grpcurl list` against a learner).
    let descriptors =
        std::path::PathBuf::from(std::env::var("OUT_DIR")?).join("socialflow_descriptor.bin");
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .file_descriptor_set_path(descriptors)
        .compile_protos(&[file], &[root])?;
    Ok(())
}
