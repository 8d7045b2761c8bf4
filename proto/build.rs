//! Compiles `haptics/v1/*.proto` with protox (pure Rust), so a fresh machine needs no `protoc`.
//! The encoded descriptor set is also written to OUT_DIR for gRPC server reflection.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let files = ["haptics/v1/haptics.proto"];
    for f in &files {
        println!("cargo:rerun-if-changed={f}");
    }
    let fds = protox::compile(files, ["."])?;
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    let bytes = prost::Message::encode_to_vec(&fds);
    std::fs::write(out.join("haptics_v1_descriptor.bin"), bytes)?;
    tonic_prost_build::configure()
        .build_server(true)
        .build_client(true)
        // The fixed RPC name `DeviceLink.Connect` would collide with the generated
        // `XClient::connect(endpoint)` constructor; clients use `XClient::new(channel)` instead.
        .build_transport(false)
        // Undecodable messages (bad protobuf, non-UTF-8 strings) are INVALID_ARGUMENT, not
        // INTERNAL (src/codec.rs).
        .codec_path("crate::codec::ProtoCodec")
        // `SurfaceFrame.position_delta` as `bytes::Bytes`: one encoding shared by every watcher.
        .bytes(".haptics.v1.SurfaceFrame.position_delta")
        .bytes(".haptics.v1.SurfaceFrame.reference_delta")
        // `prost::Name` impls (full names such as `haptics.v1.SurfaceFrame`): the schema names
        // of MCAP recordings (src/recording.rs).
        .compile_fds_with_config(fds, {
            let mut config = tonic_prost_build::Config::new();
            config.enable_type_names();
            config
        })?;
    Ok(())
}
