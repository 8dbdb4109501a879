//! echosurf-live: tracked frames streamed over OpenIGTLink (from PlusServer or any peer) become a
//! recorded sweep and a surface that is refitted as they arrive and sent back as POLYDATA.
//!
//! [`codec`] reads and writes the wire format (bounded, never panics on bad bytes), [`session`] pairs
//! images with poses, records them and refits the surface, [`client`] runs the connection.

pub mod client;
pub mod codec;
pub mod crc64;
pub mod session;
