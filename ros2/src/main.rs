//! `semlook_node`: semlook as a ROS 2 node. Subscribes camera frames (`sensor_msgs/Image`:
//! rgb8, bgr8, mono8; `sensor_msgs/CompressedImage`: jpeg, png) with the sensor-data QoS,
//! localizes each against a map with the streaming localizer (sequence matching on by default;
//! loop-closure mode on a growing map), and publishes a `semlook_msgs/PlaceMatch` for every frame
//! it localizes on `~/match`, and in loop-closure mode a `semlook_msgs/LoopClosure` on `~/closure`.
//! With `camera_info` (a file) or `camera_info_topic` (`sensor_msgs/CameraInfo`, usually
//! `/camera/camera_info`) accepted matches carry the frame's pose relative to the place's.
//!
//! ```sh
//! semlook_node --ros-args -p map:=/data/my-map -p setting:=verified -r __node:=semlook
//! ```
//!
//! Frames arrive on the DDS thread and wait in a queue of `queue_size` frames; when the localizer
//! is slower than the camera the oldest waiting frame is dropped (counted, never buffered without
//! bound). Every `map_refresh_s` the node moves to the map's newest generation if another writer
//! committed one, else keeps the one it has. Built on ros2-client (RustDDS, pure Rust): cargo
//! alone builds it, no ROS installation. DDS stays on this host when `ROS_AUTOMATIC_DISCOVERY_RANGE`
//! is `LOCALHOST` (or `ROS_LOCALHOST_ONLY=1`), as ROS 2 nodes do.

mod error;
mod msgs;
mod node;
mod params;

fn main() {
    // Mesa's Vulkan loader prints `error: XDG_RUNTIME_DIR is invalid or not set` when it is unset
    // (headless machines; the default backend `auto` looks for a GPU); it is not used for
    // compute. Set before any thread starts, as the semlook command line does.
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        // SAFETY: single-threaded here, at the very start of main.
        unsafe { std::env::set_var("XDG_RUNTIME_DIR", std::env::temp_dir()) };
    }
    node::init_logging();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let params = match params::Params::parse(&args) {
        Ok(Some(p)) => p,
        Ok(None) => {
            println!("{}", params::USAGE);
            return;
        }
        Err(e) => {
            eprintln!("semlook_node: {e}\n\n{}", params::USAGE);
            std::process::exit(2);
        }
    };
    if let Err(e) = node::run(params) {
        log::error!("{e}");
        if let Some(hint) = e.hint() {
            log::error!("hint: {hint}");
        }
        std::process::exit(1);
    }
}
