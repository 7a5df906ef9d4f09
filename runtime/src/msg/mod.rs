//! Message types. ROS 2 types keep their exact layouts; our own types use the
//! same CDR encoding. Encode and decode with [`crate::codec`].

mod gym;
mod robot;
mod ros;

pub use gym::*;
pub use robot::*;
pub use ros::*;
