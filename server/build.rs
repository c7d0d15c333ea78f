//! Compiles `proto/dinerdash/v1/dinerdash.proto` with protox (no system `protoc`) into the
//! tonic client and server, and writes the encoded descriptor set that server reflection serves.
//! The files belong to the `dinerdash-proto` build dependency (so the sdist carries them).

use std::path::PathBuf;

use prost::Message as _;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // The dinerdash-proto crate's folder: beside this package here and in the sdist.
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR")?).join("../proto");
    let proto = root.join(dinerdash_proto::FILE);
    println!("cargo:rerun-if-changed={}", proto.display());
    let fds = protox::compile([&proto], [&root])?;
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("dinerdash_descriptor.bin"), fds.encode_to_vec())?;
    // Undecodable requests are INVALID_ARGUMENT, not prost's INTERNAL (src/codec.rs).
    tonic_prost_build::configure()
        .codec_path("crate::codec::StrictCodec")
        // Its Debug is written by hand (service/convert.rs): it must not print shm_secret.
        .skip_debug([".dinerdash.v1.CreateSessionResponse"])
        // The web endpoint's games read and write a configuration as JSON in these names.
        .type_attribute(
            ".dinerdash.v1.GameConfig",
            "#[derive(serde::Serialize, serde::Deserialize)] #[serde(deny_unknown_fields)]",
        )
        .emit_rerun_if_changed(false)
        .compile_fds(fds)?;
    Ok(())
}
