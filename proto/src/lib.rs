//! The contract between ebmpc processes: the task catalog, the messages, the key expressions
//! they travel on, the codec that turns them into bytes, the validation every received message
//! goes through, the JSON schema of the messages, the tokens that tell an agent from anyone using its name, how a process joins the Zenoh session, and how it is asked to stop.

pub mod codec;
pub mod keys;
pub mod messages;
pub mod schema;
pub mod session;
pub mod shutdown;
pub mod task;
pub mod token;
pub mod validate;

pub use codec::{CodecError, Encoding, decode, encode};
pub use keys::{AgentChannel, Keys, validate_name};
pub use messages::*;
pub use task::{Builtin, Task, TaskCatalog, TaskSpec, UnknownTask};
pub use token::{TokenError, draw_token};
