//! Recordings others can open: MCAP files (<https://mcap.dev>) whose channels carry `haptics.v1`
//! messages as protobuf with the contract's `FileDescriptorSet` as schema, so Foxglove (and any
//! MCAP reader with protobuf support) decodes them without our code.
//!
//! Topics ([`topic`]): `/surface` (`SurfaceFrame`, from `hapticctl record`), `/stats`
//! (`SessionStats`, same), `/device/sample` (`DeviceSample`, from `haptic-bridge --record
//! FILE.mcap`), `/device/force` (`ForceCommand`, the force the bridge rendered, same). Log
//! times are nanoseconds: wall clock (UNIX epoch) for `hapticctl`, time since the bridge
//! started for the bridge (its `device_time_us` carries the same clock).
//!
//! Neighbours: written by `hapticctl record` and `haptic-bridge`; read by `haptic-bridge
//! --driver replay`, `haptic-viewer --replay` and `hapticctl export-vtu`.

use std::collections::{BTreeMap, HashMap};
use std::io::{Seek, Write};

use prost::{Message, Name};

/// Topic names.
pub mod topic {
    /// `haptics.v1.SurfaceFrame`, full encoding.
    pub const SURFACE: &str = "/surface";
    /// `haptics.v1.SessionStats`.
    pub const STATS: &str = "/stats";
    /// `haptics.v1.DeviceSample`: the poses the bridge read.
    pub const DEVICE_SAMPLE: &str = "/device/sample";
    /// `haptics.v1.ForceCommand`: the force the bridge wrote to the device, after its guard.
    pub const DEVICE_FORCE: &str = "/device/force";
    /// `haptics.v1.AppliedForce`: each load injected by `ApplyForce`, once, at the server time
    /// of the first frame that listed it.
    pub const LOADS: &str = "/loads";
}

/// What went wrong with a recording.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    /// The MCAP layer (I/O, a malformed file).
    #[error("MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    /// A message on `topic` does not decode as the expected type.
    #[error("message {index} on {topic} does not decode as {type_name}: {source}")]
    Decode {
        /// Topic.
        topic: String,
        /// Position among that topic's messages.
        index: usize,
        /// Expected message type.
        type_name: String,
        /// Decoder error.
        source: prost::DecodeError,
    },
    /// A channel's schema is not the expected message type.
    #[error("{topic} carries {found:?}, expected {expected}")]
    WrongSchema {
        /// Topic.
        topic: String,
        /// Schema name found.
        found: String,
        /// Expected message type.
        expected: String,
    },
}

/// Writes `haptics.v1` messages to an MCAP file (uncompressed chunks, indexed).
pub struct Recorder<W: Write + Seek> {
    writer: mcap::Writer<W>,
    channels: HashMap<String, u16>,
    sequence: u32,
}

impl<W: Write + Seek> Recorder<W> {
    /// Starts a recording on `w` (a file: the summary is written at [`Recorder::finish`]).
    ///
    /// # Errors
    /// [`RecordingError::Mcap`] when the header cannot be written.
    pub fn new(w: W) -> Result<Self, RecordingError> {
        let options = mcap::WriteOptions::new().profile("haptics");
        Ok(Self {
            writer: options.create(w)?,
            channels: HashMap::new(),
            sequence: 0,
        })
    }

    /// Appends `message` on `topic` at `log_time_ns`. The channel and its schema (the message's
    /// full name, the contract's `FileDescriptorSet`) are added on first use.
    ///
    /// # Errors
    /// [`RecordingError::Mcap`] on I/O errors.
    pub fn write<M: Message + Name>(
        &mut self,
        topic: &str,
        log_time_ns: u64,
        message: &M,
    ) -> Result<(), RecordingError> {
        let channel_id = match self.channels.get(topic) {
            Some(&id) => id,
            None => {
                let schema = self.writer.add_schema(
                    &M::full_name(),
                    "protobuf",
                    haptics_proto::FILE_DESCRIPTOR_SET,
                )?;
                let id = self
                    .writer
                    .add_channel(schema, topic, "protobuf", &BTreeMap::new())?;
                self.channels.insert(topic.to_string(), id);
                id
            }
        };
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: self.sequence,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        self.writer
            .write_to_known_channel(&header, &message.encode_to_vec())?;
        Ok(())
    }

    /// Writes the summary and index and flushes.
    ///
    /// # Errors
    /// [`RecordingError::Mcap`] on I/O errors.
    pub fn finish(mut self) -> Result<(), RecordingError> {
        self.writer.finish()?;
        Ok(())
    }
}

/// The messages on `topic` of the MCAP file `bytes`, decoded as `M`, with their log times (ns),
/// in file order. A topic that is absent gives an empty list.
///
/// # Errors
/// [`RecordingError::Mcap`] for a malformed file, [`RecordingError::WrongSchema`] when the
/// topic's schema is another type, [`RecordingError::Decode`] for a message that does not
/// decode.
pub fn read_topic<M: Message + Name + Default>(
    bytes: &[u8],
    topic: &str,
) -> Result<Vec<(u64, M)>, RecordingError> {
    let mut out = Vec::new();
    for message in mcap::MessageStream::new(bytes)? {
        let message = message?;
        if message.channel.topic != topic {
            continue;
        }
        let expected = M::full_name();
        let found = message
            .channel
            .schema
            .as_ref()
            .map_or(String::new(), |s| s.name.clone());
        if found != expected {
            return Err(RecordingError::WrongSchema {
                topic: topic.to_string(),
                found,
                expected,
            });
        }
        let decoded =
            M::decode(message.data.as_ref()).map_err(|source| RecordingError::Decode {
                topic: topic.to_string(),
                index: out.len(),
                type_name: expected.clone(),
                source,
            })?;
        out.push((message.log_time, decoded));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use haptics_proto::v1::{DeviceSample, SessionStats, SurfaceFrame, Vec3};

    #[test]
    fn messages_round_trip_by_topic_with_schemas_and_times() {
        let mut buf = std::io::Cursor::new(Vec::new());
        let mut r = Recorder::new(&mut buf).unwrap();
        for i in 0..5u64 {
            let sample = DeviceSample {
                seq: i,
                position_m: Some(Vec3::new(0.01 * i as f64, 0.0, -0.005)),
                ..Default::default()
            };
            r.write(topic::DEVICE_SAMPLE, 1_000_000 * i, &sample)
                .unwrap();
        }
        let frame = SurfaceFrame {
            keyframe: true,
            positions_m: vec![1.0, 2.0, 3.0],
            triangles: vec![0, 0, 0],
            ..Default::default()
        };
        r.write(topic::SURFACE, 7, &frame).unwrap();
        r.finish().unwrap();
        let bytes = buf.into_inner();
        assert_eq!(&bytes[..8], b"\x89MCAP0\r\n", "MCAP magic");

        let samples = read_topic::<DeviceSample>(&bytes, topic::DEVICE_SAMPLE).unwrap();
        assert_eq!(samples.len(), 5);
        assert_eq!(samples[3].0, 3_000_000);
        assert_eq!(samples[3].1.position_m.unwrap().x, 0.03);
        let frames = read_topic::<SurfaceFrame>(&bytes, topic::SURFACE).unwrap();
        assert_eq!(frames, vec![(7, frame)]);
        assert!(
            read_topic::<SessionStats>(&bytes, topic::STATS)
                .unwrap()
                .is_empty()
        );
        // The schema is the message's full name: asking for another type is refused.
        let e = read_topic::<SessionStats>(&bytes, topic::SURFACE).unwrap_err();
        assert!(matches!(e, RecordingError::WrongSchema { .. }), "{e}");
        // Readers see the schema as Foxglove does: protobuf, the FileDescriptorSet, full name.
        let summary = mcap::Summary::read(&bytes).unwrap().expect("summary");
        let names: Vec<_> = summary.schemas.values().map(|s| s.name.clone()).collect();
        assert!(
            names.contains(&"haptics.v1.DeviceSample".to_string()),
            "{names:?}"
        );
        for s in summary.schemas.values() {
            assert_eq!(s.encoding, "protobuf");
            assert_eq!(s.data.as_ref(), haptics_proto::FILE_DESCRIPTOR_SET);
        }
    }

    #[test]
    fn garbage_is_an_error_not_a_panic() {
        assert!(read_topic::<SurfaceFrame>(b"not an mcap file", topic::SURFACE).is_err());
        assert!(read_topic::<SurfaceFrame>(b"\x89MCAP0\r\n\x01\x02", topic::SURFACE).is_err());
    }
}
