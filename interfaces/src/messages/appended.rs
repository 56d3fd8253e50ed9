//! Optional fields appended by a minor version: readable from messages that predate them.
//!
//! A minor version appends `Option` fields at the end of a message. On the wire such a field
//! is postcard's `Option` (a 0/1 byte, then the value), and it is left out entirely when it
//! is `None` (`skip_serializing_if`), so a message without it is byte-identical to the older
//! version and older receivers read it unchanged. [`deserialize`] reads the field back:
//! - no byte left at all (a message from an older sender): `None`;
//! - `0` (also CAN FD zero padding after an older message): `None`;
//! - `1` then the value: `Some(value)`, and a value cut short is a format error, never a
//!   silent `None`;
//! - any other tag byte: a format error.
//!
//! Invariant: only the very first byte of the field may be missing; this relies on postcard
//! reading a `u8` as one raw byte (its only failure is the end of input), so it is for
//! postcard-encoded catalogue messages only.

use core::fmt;
use core::marker::PhantomData;
use serde::de::{Deserialize, Deserializer, Error, SeqAccess, Visitor};

struct AppendedVisitor<T>(PhantomData<T>);

impl<'de, T: Deserialize<'de>> Visitor<'de> for AppendedVisitor<T> {
    type Value = Option<T>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("an optional appended field")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        // The only way a raw byte read fails is the end of the message: an older sender.
        let Ok(tag) = seq.next_element::<u8>() else {
            return Ok(None);
        };
        match tag {
            None | Some(0) => Ok(None),
            Some(1) => match seq.next_element::<T>()? {
                Some(value) => Ok(Some(value)),
                None => Err(A::Error::custom("appended field without its value")),
            },
            Some(_) => Err(A::Error::custom("appended field with a bad Option tag")),
        }
    }
}

/// `deserialize_with` for an appended `Option<T>` field (see the module header).
pub fn deserialize<'de, D, T>(deserializer: D) -> Result<Option<T>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    // A two-element tuple: the Option tag, then (only when the tag is 1) the value.
    deserializer.deserialize_tuple(2, AppendedVisitor(PhantomData))
}
