//! Frames of episodes as PNG files, drawn offscreen by MuJoCo (cargo feature `render`, off by
//! default: it links OpenGL through EGL, which CI machines and servers may lack).
//!
//! Rendering runs on a thread of its own with its own copy of the model. An OpenGL context is
//! current on one thread at a time, while the bridge's async loop may resume on any worker
//! thread; and the control loop only hands over each frame's generalised positions, so it never
//! waits for the GPU unless the renderer falls a whole queue behind. The thread recomputes the
//! scene from those positions and writes `DIR/episode-EEE/frame-SSSS.png`, episodes counted from
//! 0 in the order this process runs them.
//!
//! Without a usable context (no EGL library, no GPU and no Mesa software renderer, a sandbox
//! without `/dev/dri`), [`FrameRecorder::start`] says why and the caller carries on without
//! frames.

use mujoco_rs::prelude::{MjData, MjModel, MjvCamera};
use mujoco_rs::renderer::{MjRenderer, png};
use std::error::Error;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, Receiver, SyncSender};
use std::thread::JoinHandle;

/// Frame size in pixels.
const WIDTH: u32 = 480;
const HEIGHT: u32 = 360;
/// Frames queued for the render thread before the simulation waits for it.
const QUEUE: usize = 64;

/// Why frames cannot be recorded.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("cannot create the frames folder {path}: {source}")]
    Folder {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "no offscreen OpenGL context (headless rendering needs EGL, with a GPU driver or Mesa's \
         software renderer): {0}"
    )]
    NoContext(String),
    #[error("the renderer could not load the model: {0}")]
    Model(String),
}

/// What the simulation sends the render thread.
enum Message {
    /// The next frames belong to a new episode.
    Episode,
    /// Generalised positions of one frame.
    Frame(Vec<f64>),
}

/// Records frames of a task's episodes on a render thread; dropping it waits for the frames
/// still queued to be written.
pub struct FrameRecorder {
    /// `None` once the render thread has stopped (it logged why).
    queue: Option<SyncSender<Message>>,
    thread: Option<JoinHandle<()>>,
    dir: PathBuf,
}

impl std::fmt::Debug for FrameRecorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameRecorder")
            .field("dir", &self.dir)
            .field("recording", &self.queue.is_some())
            .finish()
    }
}

impl FrameRecorder {
    /// Starts a render thread for the model `xml` that writes frames under `dir`; returns once
    /// the thread holds an OpenGL context, or with the reason it could not get one.
    pub fn start(xml: &'static str, dir: &Path) -> Result<Self, RenderError> {
        std::fs::create_dir_all(dir).map_err(|source| RenderError::Folder {
            path: dir.to_path_buf(),
            source,
        })?;
        let (ready_tx, ready_rx) = mpsc::channel();
        let (queue, frames) = mpsc::sync_channel(QUEUE);
        let out = dir.to_path_buf();
        let thread = std::thread::Builder::new()
            .name("render".into())
            .spawn(move || match Painter::new(xml) {
                Ok(painter) => {
                    // The receiver waits for this answer, so a failed send cannot happen.
                    let _ = ready_tx.send(Ok(()));
                    painter.run(frames, &out);
                }
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                }
            })
            .map_err(|e| RenderError::NoContext(format!("cannot start the render thread: {e}")))?;
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(Self {
                queue: Some(queue),
                thread: Some(thread),
                dir: dir.to_path_buf(),
            }),
            Ok(Err(e)) => {
                let _ = thread.join();
                Err(e)
            }
            Err(_) => {
                let _ = thread.join();
                Err(RenderError::NoContext(
                    "the render thread stopped while creating its context".into(),
                ))
            }
        }
    }

    /// Where the frames go.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Starts a new episode's folder for the frames that follow.
    pub fn begin_episode(&mut self) {
        self.send(Message::Episode);
    }

    /// Queues a frame of the system at generalised positions `qpos`.
    pub fn capture(&mut self, qpos: &[f64]) {
        self.send(Message::Frame(qpos.to_vec()));
    }

    fn send(&mut self, message: Message) {
        if let Some(queue) = &self.queue
            && queue.send(message).is_err()
        {
            // The thread has stopped on an error and logged it: stop recording quietly.
            self.queue = None;
        }
    }
}

impl Drop for FrameRecorder {
    fn drop(&mut self) {
        // Closing the queue ends the thread once it has written what is queued.
        self.queue = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// The render thread's model, state and renderer.
struct Painter {
    data: MjData<Box<MjModel>>,
    renderer: MjRenderer,
}

impl Painter {
    fn new(xml: &str) -> Result<Self, RenderError> {
        let model = MjModel::from_xml_string(xml).map_err(|e| RenderError::Model(chain(&e)))?;
        // Follow the model's first body (cart, torso, arm), from MuJoCo's default free view of
        // the whole model: runners stay in the picture.
        let mut camera = MjvCamera::new_free(&model);
        camera.track(1);
        let data = MjData::new(Box::new(model));
        let renderer = MjRenderer::builder()
            .width(WIDTH)
            .height(HEIGHT)
            .camera(camera)
            .png_compression(png::Compression::Fast)
            .build(data.model())
            .map_err(|e| RenderError::NoContext(chain(&e)))?;
        Ok(Self { data, renderer })
    }

    /// Draws and writes every frame received until the queue closes or writing fails.
    fn run(mut self, frames: Receiver<Message>, dir: &Path) {
        let mut episode: Option<(PathBuf, u32)> = None;
        let mut episodes = 0u32;
        for message in frames {
            let qpos = match message {
                Message::Episode => {
                    let folder = dir.join(format!("episode-{episodes:03}"));
                    episodes += 1;
                    if let Err(e) = std::fs::create_dir_all(&folder) {
                        tracing::warn!("--render: cannot create {}: {e}", folder.display());
                        return;
                    }
                    episode = Some((folder, 0));
                    continue;
                }
                Message::Frame(qpos) => qpos,
            };
            let Some((folder, frame)) = episode.as_mut() else {
                continue;
            };
            let path = folder.join(format!("frame-{frame:04}.png"));
            *frame += 1;
            if let Err(e) = self.draw(&qpos, &path) {
                tracing::warn!("--render: stopped at {}: {e}", path.display());
                return;
            }
        }
    }

    fn draw(&mut self, qpos: &[f64], path: &Path) -> Result<(), String> {
        self.data.qpos_mut().copy_from_slice(qpos);
        // Positions of bodies, geoms, cameras and lights, and the centres of mass the tracking
        // camera follows.
        self.data.forward_kinematics();
        self.renderer
            .sync_data(&mut self.data)
            .and_then(|()| self.renderer.render())
            .and_then(|()| self.renderer.save_rgb(path))
            .map_err(|e| chain(&e))
    }
}

/// An error and its sources, `outer: inner: …`.
fn chain(error: &dyn Error) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(inner) = source {
        text.push_str(": ");
        text.push_str(&inner.to_string());
        source = inner.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use crate::Env;
    use crate::render::RenderError;
    use proto::Builtin;

    /// On a machine with an offscreen context, an episode's states come out as PNG files, one
    /// folder per episode; without one, recording is refused with the reason and the
    /// environment runs on.
    #[test]
    fn frames_of_an_episode_or_a_clear_reason() {
        let dir = std::env::temp_dir().join(format!("sim-bridge-render-{}", std::process::id()));
        let mut env = Env::new(Builtin::Pusher).unwrap();
        let recording = env.record_frames(&dir);
        env.reset(1);
        for _ in 0..3 {
            env.step(&[1.0; 7]).unwrap();
        }
        env.reset(2);
        env.step(&[0.0; 7]).unwrap();
        drop(env);
        match recording {
            Ok(()) => {
                for (episode, frames) in [(0, 4), (1, 2)] {
                    let folder = dir.join(format!("episode-{episode:03}"));
                    let mut names: Vec<_> = std::fs::read_dir(&folder)
                        .unwrap()
                        .map(|e| e.unwrap().file_name().into_string().unwrap())
                        .collect();
                    names.sort();
                    let expected: Vec<_> =
                        (0..frames).map(|f| format!("frame-{f:04}.png")).collect();
                    assert_eq!(names, expected, "{}", folder.display());
                    let png = std::fs::read(folder.join(&names[0])).unwrap();
                    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n") && png.len() > 1000);
                }
            }
            Err(RenderError::NoContext(reason)) => {
                assert!(!reason.is_empty());
                let message = RenderError::NoContext(reason).to_string();
                assert!(message.contains("EGL"), "{message}");
            }
            Err(e) => panic!("{e}"),
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
