//! The connection: a reader thread turns the socket into decoded messages on a bounded queue, the
//! session thread records them and hands snapshots to one surface worker (a new snapshot only when the
//! worker is free, so a slow fit skips ahead while every frame is still recorded), and each finished
//! surface goes back as a POLYDATA message. Broken framing (bad header, oversized body, a connection
//! that drops mid-message) reconnects with back-off; a bad CRC or content drops that message only.

use std::io::Write;
use std::net::{Shutdown, TcpListener, TcpStream, ToSocketAddrs};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use echosurf::io::{Calibration, TrackedSequence};
use echosurf::mesh::Mesh;
use echosurf::pipeline::ExtractOptions;
use echosurf::segment::crests::CrestCache;

use crate::codec::{self, CodecError, Limits, encode_message, encode_polydata};
use crate::session::{
    IncrementalBands, LiveSession, SessionOptions, add_echo_crests, surface_of_reusing,
    update_surface_unless_stopped,
};

/// Device name of the surface sent back.
pub const SURFACE_DEVICE: &str = "EchosurfSurface";

/// A handle the application keeps to stop a running session from elsewhere (a Ctrl-C handler): the
/// session then writes what it recorded. Cloning shares the one flag.
#[derive(Debug, Clone, Default)]
pub struct StopSignal(Arc<AtomicBool>);

impl StopSignal {
    /// Asks the session to stop; returns false when a stop was already asked.
    pub fn request(&self) -> bool {
        !self.0.swap(true, Ordering::SeqCst)
    }

    /// Whether a stop was asked.
    pub fn requested(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
}

/// Where the frames come from: connect to a server (PlusServer), or listen and let the sender connect.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Endpoint {
    /// HOST:PORT of an OpenIGTLink server.
    Connect(String),
    /// Address to listen on (HOST:PORT; port 0 picks a free one, printed when listening).
    Listen(String),
}

impl std::fmt::Display for Endpoint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Endpoint::Connect(a) => write!(f, "{a}"),
            Endpoint::Listen(a) => write!(f, "clients on {a}"),
        }
    }
}

/// Everything a live run needs.
#[derive(Debug, Clone)]
pub struct LiveOptions {
    pub endpoint: Endpoint,
    pub session: SessionOptions,
    pub calibration: Calibration,
    pub out_dir: PathBuf,
    /// Stop after this many recorded frames.
    pub max_frames: Option<usize>,
    pub update_extract: ExtractOptions,
    pub final_extract: ExtractOptions,
    pub limits: Limits,
    /// Give up after this many connection attempts in a row fail.
    pub max_reconnects: usize,
    /// First wait before reconnecting (doubled each failure, at most 5 s).
    pub first_backoff: Duration,
    /// Protocol version of the POLYDATA messages sent back.
    pub send_version: u16,
    /// Also refit when this long has passed since the last update began and new frames came
    /// (`None`: frame counts only).
    pub update_every: Option<Duration>,
    /// Stops the run from outside (see [`StopSignal`]).
    pub stop: StopSignal,
}

/// One surface update.
#[derive(Debug, Clone, PartialEq)]
pub struct UpdateRecord {
    pub frames: usize,
    pub triangles: usize,
    /// From handing the snapshot to the worker to the mesh being ready.
    pub seconds: f64,
    /// Whether the POLYDATA message went out.
    pub sent: bool,
}

/// What a live run did.
#[derive(Debug, Clone)]
pub struct LiveSummary {
    pub frames: usize,
    pub frames_with_pose: usize,
    pub updates: Vec<UpdateRecord>,
    pub warnings: Vec<String>,
    pub connections: usize,
    pub sequence_path: PathBuf,
    pub mesh_path: PathBuf,
    pub final_triangles: usize,
    /// From the last frame's arrival to the final mesh written.
    pub last_frame_to_mesh_s: f64,
    /// Why the run ended.
    pub ended: String,
}

enum NetEvent {
    Message(Box<codec::Decoded>),
    /// A message dropped; the stream goes on.
    Dropped(String),
    /// The connection is gone: `clean` when the peer closed between messages.
    Closed {
        reason: String,
        clean: bool,
    },
}

/// Reads messages until the connection fails; decoded ones go on the bounded queue (blocking when the
/// session is behind, which holds the sender back through TCP rather than dropping frames).
fn reader_loop(mut stream: TcpStream, limits: Limits, tx: SyncSender<NetEvent>) {
    loop {
        let event = match codec::read_message(&mut stream, &limits) {
            Ok(raw) => match codec::decode(&raw) {
                Ok(decoded) => NetEvent::Message(Box::new(decoded)),
                Err(e) => NetEvent::Dropped(format!("dropped a message: {e}")),
            },
            Err(e) if e.framing_intact() => NetEvent::Dropped(format!("dropped a message: {e}")),
            Err(CodecError::Io(e)) if e.kind() == std::io::ErrorKind::UnexpectedEof => {
                NetEvent::Closed {
                    reason: e.to_string(),
                    // read_exact of the header hits EOF with nothing read when the peer closed cleanly;
                    // a body cut short says "closed N bytes into".
                    clean: !e.to_string().contains("bytes into"),
                }
            }
            Err(e) => NetEvent::Closed {
                reason: e.to_string(),
                clean: false,
            },
        };
        let closed = matches!(event, NetEvent::Closed { .. });
        if tx.send(event).is_err() || closed {
            return;
        }
    }
}

struct Worker {
    jobs: SyncSender<(TrackedSequence, Instant)>,
    results: Receiver<(usize, echosurf::Result<Mesh>, f64)>,
    busy: bool,
    /// Set when the session ends: an update still running is abandoned so the final mesh has the
    /// cores to itself.
    stop: Arc<AtomicBool>,
}

/// The update worker: each job is an update of the surface, then the echo crests of the new frames as
/// the final mesh (`final_options`) reads them, into `crests`.
fn start_worker(
    calibration: Calibration,
    options: ExtractOptions,
    final_options: ExtractOptions,
    crests: Arc<Mutex<CrestCache>>,
) -> Worker {
    let (jobs, job_rx) = mpsc::sync_channel::<(TrackedSequence, Instant)>(1);
    let (result_tx, results) = mpsc::channel();
    let stop = Arc::new(AtomicBool::new(false));
    let stop_seen = Arc::clone(&stop);
    std::thread::spawn(move || {
        let mut bands = IncrementalBands::default();
        for (sequence, started) in job_rx {
            let Some(mesh) = update_surface_unless_stopped(
                &mut bands,
                &sequence,
                &calibration,
                &options,
                &stop_seen,
            ) else {
                return;
            };
            let seconds = started.elapsed().as_secs_f64();
            if result_tx
                .send((sequence.frames.len(), mesh, seconds))
                .is_err()
            {
                return;
            }
            // A failure here is the final mesh's to report (it finds the crests itself then).
            if let Ok(mut crests) = crests.lock() {
                let _ = add_echo_crests(
                    &sequence,
                    &calibration,
                    &final_options,
                    &mut crests,
                    &stop_seen,
                );
            }
        }
    });
    Worker {
        jobs,
        results,
        busy: false,
        stop,
    }
}

fn polydata_message(mesh: &Mesh, version: u16, message_id: u32) -> Option<Vec<u8>> {
    let content = encode_polydata(&mesh.vertices, &mesh.triangles)?;
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0);
    Some(encode_message(
        version,
        "POLYDATA",
        SURFACE_DEVICE,
        now,
        &content,
        &[],
        message_id,
    ))
}

/// Connects, retrying with doubling waits; `None` after `max_reconnects` failures or a stop request.
fn connect_with_backoff(
    address: &str,
    options: &LiveOptions,
    warnings: &mut Vec<String>,
) -> Option<TcpStream> {
    let mut wait = options.first_backoff;
    for attempt in 1..=options.max_reconnects.max(1) {
        if options.stop.requested() {
            return None;
        }
        let addrs = address.to_socket_addrs();
        let result = addrs.map_err(|e| e.to_string()).and_then(|mut a| {
            let addr = a.next().ok_or_else(|| "no address".to_string())?;
            TcpStream::connect_timeout(&addr, Duration::from_secs(5)).map_err(|e| e.to_string())
        });
        match result {
            Ok(stream) => return Some(stream),
            Err(e) => {
                let message = format!("connecting to {address} (attempt {attempt}): {e}");
                eprintln!("warning: {message}");
                warnings.push(message);
                std::thread::sleep(wait);
                wait = (wait * 2).min(Duration::from_secs(5));
            }
        }
    }
    None
}

/// Waits for a sender to connect: without a limit for the first one, then (after a lost connection)
/// as long as the reconnect schedule of a client would try; `None` then or on a stop request.
fn accept_with_deadline(
    listener: &TcpListener,
    first: bool,
    options: &LiveOptions,
) -> Option<TcpStream> {
    let mut patience = Duration::ZERO;
    let mut wait = options.first_backoff;
    for _ in 0..options.max_reconnects.max(1) {
        patience += wait;
        wait = (wait * 2).min(Duration::from_secs(5));
    }
    let started = Instant::now();
    loop {
        if options.stop.requested() || (!first && started.elapsed() > patience) {
            return None;
        }
        match listener.accept() {
            Ok((stream, _)) => {
                // The listener polls; the accepted stream blocks as a connected client's does.
                return stream.set_nonblocking(false).is_ok().then_some(stream);
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(20));
            }
            Err(e) => {
                eprintln!("warning: accepting a connection: {e}");
                std::thread::sleep(Duration::from_millis(20));
            }
        }
    }
}

/// The source of connections: a server's address to (re)connect to, or our listening socket.
enum Source {
    Connect(String),
    Listen(TcpListener),
}

impl Source {
    fn open(endpoint: &Endpoint) -> echosurf::Result<Source> {
        match endpoint {
            Endpoint::Connect(address) => Ok(Source::Connect(address.clone())),
            Endpoint::Listen(address) => {
                let fail = |e: std::io::Error| {
                    echosurf::Error::InvalidInput(format!("listening on {address}: {e}"))
                };
                let listener = TcpListener::bind(address.as_str()).map_err(fail)?;
                listener.set_nonblocking(true).map_err(fail)?;
                let local = listener.local_addr().map_err(fail)?;
                eprintln!("listening on {local}");
                Ok(Source::Listen(listener))
            }
        }
    }

    fn next(
        &self,
        first: bool,
        options: &LiveOptions,
        warnings: &mut Vec<String>,
    ) -> Option<TcpStream> {
        match self {
            Source::Connect(address) => connect_with_backoff(address, options, warnings),
            Source::Listen(listener) => accept_with_deadline(listener, first, options),
        }
    }
}

/// Runs the session until the server closes, `max_frames` are recorded, a stop is requested or the
/// server cannot be reached; then writes the sequence and the final mesh into `out_dir`.
pub fn run(options: &LiveOptions) -> echosurf::Result<LiveSummary> {
    let sequence_path = options.out_dir.join("live.igs.mha");
    let mesh_path = options.out_dir.join("live_surface.ply");
    let mut session = LiveSession::new(options.session.clone());
    let mut warnings: Vec<String> = Vec::new();
    let warn = |w: String, all: &mut Vec<String>| {
        eprintln!("warning: {w}");
        all.push(w);
    };
    // The frames' echo crests for the final mesh, found by the worker after its updates.
    let crests = Arc::new(Mutex::new(CrestCache::default()));
    let new_worker = || {
        start_worker(
            options.calibration.clone(),
            options.update_extract.clone(),
            options.final_extract.clone(),
            Arc::clone(&crests),
        )
    };
    let mut worker = new_worker();
    let mut updates = Vec::new();
    let mut connections = 0;
    let mut message_id = 0u32;
    let mut last_frame_at = Instant::now();
    let mut last_update_at = Instant::now();
    let source = Source::open(&options.endpoint)?;
    let ended;
    // Set when the run stops at `max_frames`: the peer then gets the final surface too.
    let mut final_writer = None;
    'connections: loop {
        let Some(stream) = source.next(connections == 0, options, &mut warnings) else {
            ended = match &options.endpoint {
                _ if options.stop.requested() => "stopped (Ctrl-C)".to_string(),
                Endpoint::Connect(address) => format!("could not reach {address}"),
                Endpoint::Listen(_) => "no sender reconnected".to_string(),
            };
            break;
        };
        connections += 1;
        let _ = stream.set_nodelay(true);
        let mut writer = stream
            .try_clone()
            .map_err(|e| echosurf::Error::io(Path::new(&options.endpoint.to_string()), e))?;
        let _ = writer.set_write_timeout(Some(Duration::from_secs(2)));
        let (tx, rx) = mpsc::sync_channel(256);
        let limits = options.limits;
        let reader = std::thread::spawn(move || reader_loop(stream, limits, tx));
        loop {
            if options.stop.requested() {
                let _ = writer.shutdown(Shutdown::Both);
                let _ = reader.join();
                ended = "stopped (Ctrl-C)".to_string();
                break 'connections;
            }
            // Finished surfaces go back to the peer.
            while let Ok((frames, mesh, seconds)) = worker.results.try_recv() {
                worker.busy = false;
                match mesh {
                    Ok(mesh) => {
                        message_id = message_id.wrapping_add(1);
                        let sent = polydata_message(&mesh, options.send_version, message_id)
                            .is_some_and(|bytes| writer.write_all(&bytes).is_ok());
                        updates.push(UpdateRecord {
                            frames,
                            triangles: mesh.triangles.len(),
                            seconds,
                            sent,
                        });
                    }
                    Err(e) => warn(
                        format!("surface update at {frames} frames failed: {e}"),
                        &mut warnings,
                    ),
                }
            }
            let time_due = options.update_every.is_some_and(|period| {
                session.frames_since_update() > 0 && last_update_at.elapsed() >= period
            });
            if (session.update_due() || time_due) && !worker.busy {
                let snapshot = session.snapshot_for_update();
                match worker.jobs.try_send((snapshot, Instant::now())) {
                    Ok(()) => {
                        worker.busy = true;
                        last_update_at = Instant::now();
                    }
                    Err(TrySendError::Full(_)) => {}
                    Err(TrySendError::Disconnected(_)) => {
                        warn("the surface worker stopped".into(), &mut warnings);
                        worker = new_worker();
                    }
                }
            }
            if options
                .max_frames
                .is_some_and(|n| session.sequence().frames.len() >= n)
            {
                // The reader stays blocked on the socket until it is shut down below.
                drop(reader);
                ended = format!(
                    "{} frames recorded (--frames)",
                    session.sequence().frames.len()
                );
                // The connection stays open for the final surface.
                final_writer = Some(writer);
                break 'connections;
            }
            match rx.recv_timeout(Duration::from_millis(20)) {
                Ok(NetEvent::Message(decoded)) => {
                    let before = session.sequence().frames.len();
                    for w in session.handle(&decoded) {
                        warn(w, &mut warnings);
                    }
                    if session.sequence().frames.len() > before {
                        last_frame_at = Instant::now();
                    }
                }
                Ok(NetEvent::Dropped(w)) => warn(w, &mut warnings),
                Ok(NetEvent::Closed { reason, clean }) => {
                    let _ = reader.join();
                    if clean {
                        ended = match options.endpoint {
                            Endpoint::Connect(_) => "the server closed the connection",
                            Endpoint::Listen(_) => "the sender closed the connection",
                        }
                        .to_string();
                        break 'connections;
                    }
                    warn(
                        format!("connection lost ({reason}): reconnecting"),
                        &mut warnings,
                    );
                    std::thread::sleep(options.first_backoff);
                    continue 'connections;
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => {
                    let _ = reader.join();
                    warn(
                        "connection reader stopped: reconnecting".into(),
                        &mut warnings,
                    );
                    continue 'connections;
                }
            }
        }
    }
    // No more updates: one still running would share the 2 cores with the final mesh.
    worker.stop.store(true, Ordering::Relaxed);
    for w in session.finish() {
        warn(w, &mut warnings);
    }
    // The worker lets go of the crests within a few frames once stopped; a worker that panicked
    // holding them leaves them as they were (each frame's crests are added whole).
    let mut crests = crests
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    let summary = finish(
        options,
        &mut session,
        (&sequence_path, &mesh_path),
        &mut crests,
        last_frame_at,
        &mut warnings,
    )?;
    if let Some(mut writer) = final_writer {
        message_id = message_id.wrapping_add(1);
        let _ = writer.set_write_timeout(Some(Duration::from_secs(10)));
        if let Some(bytes) = polydata_message(&summary.0, options.send_version, message_id) {
            let _ = writer.write_all(&bytes);
            let _ = writer.flush();
        }
        let _ = writer.shutdown(Shutdown::Both);
    }
    Ok(summarise(
        summary,
        session.sequence(),
        updates,
        warnings,
        connections,
        sequence_path,
        mesh_path,
        ended,
    ))
}

/// Writes the recording, then the final mesh (when some frame has a pose); returns the mesh and the
/// time from the last frame to the mesh on disk.
fn finish(
    options: &LiveOptions,
    session: &mut LiveSession,
    (sequence_path, mesh_path): (&Path, &Path),
    crests: &mut CrestCache,
    last_frame_at: Instant,
    warnings: &mut Vec<String>,
) -> echosurf::Result<(Mesh, f64)> {
    let sequence = session.sequence();
    if sequence.frames.is_empty() {
        return Err(echosurf::Error::InvalidInput(format!(
            "no frames were received from {}: nothing written",
            options.endpoint
        )));
    }
    echosurf::io::write_sequence(sequence_path, sequence, false)?;
    let final_mesh = surface_of_reusing(
        sequence,
        &options.calibration,
        &options.final_extract,
        crests,
    );
    let mesh = match final_mesh {
        Ok(mesh) => {
            // Tagged SPACE=RAS as `extract` writes by default (the Reference numbers unchanged).
            echosurf::io::write_mesh_in(mesh_path, &mesh, echosurf::io::Space::Ras)?;
            mesh
        }
        Err(e) => {
            let w = format!(
                "no final surface ({e}); the recorded sequence is in {}",
                sequence_path.display()
            );
            eprintln!("warning: {w}");
            warnings.push(w);
            Mesh::default()
        }
    };
    Ok((mesh, last_frame_at.elapsed().as_secs_f64()))
}

#[allow(clippy::too_many_arguments)]
fn summarise(
    (mesh, last_frame_to_mesh_s): (Mesh, f64),
    sequence: &TrackedSequence,
    updates: Vec<UpdateRecord>,
    warnings: Vec<String>,
    connections: usize,
    sequence_path: PathBuf,
    mesh_path: PathBuf,
    ended: String,
) -> LiveSummary {
    LiveSummary {
        frames: sequence.frames.len(),
        frames_with_pose: sequence
            .frames
            .iter()
            .filter(|f| f.transforms.values().any(|t| t.valid))
            .count(),
        updates,
        warnings,
        connections,
        sequence_path,
        mesh_path,
        final_triangles: mesh.triangles.len(),
        last_frame_to_mesh_s,
        ended,
    }
}
