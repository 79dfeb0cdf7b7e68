//! The feed of a network source: the session's end of a source whose packets a background
//! thread fetches (the cache's, the range reader's) — a byte-bounded queue of packets one way,
//! view changes and dropped packets the other, the thread's shared status — and the
//! [`PacketSource`] forwarding every such source makes to its feed.

use super::{PacketSource, SourceError, SourcePacket, SourceStatus};
use std::sync::{Arc, Mutex};
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};
use wavesplat_codec::view::ViewSpec;

/// What the session tells a network source's thread.
pub(crate) enum Control {
    /// The view changed.
    View(ViewSpec),
    /// The session dropped these packets.
    Dropped(Vec<u32>),
}

/// The session's end of a source fed by a network thread (the cache's, the range reader's):
/// packets arrive on a bounded channel, view changes and dropped packets go back on another,
/// and the thread's status is shared. Dropping it closes the control channel, which ends the
/// thread's task, and joins the thread.
#[derive(Debug)]
pub(crate) struct Feed {
    rx: mpsc::UnboundedReceiver<(SourcePacket, OwnedSemaphorePermit)>,
    /// The queue's room in bytes (closed when the feed is dropped, so that a task waiting
    /// for room ends).
    room: Arc<Semaphore>,
    ctl: Option<mpsc::UnboundedSender<Control>>,
    status: Arc<Mutex<SourceStatus>>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// View changes sent to the thread (see [`SourceStatus::views_applied`]).
    views_sent: u64,
}

/// The network thread's end of a feed's queue: packets wait for the session there up to a
/// byte bound (a packet larger than the bound passes alone, when the queue is empty).
#[derive(Debug, Clone)]
pub(crate) struct PacketSender {
    tx: mpsc::UnboundedSender<(SourcePacket, OwnedSemaphorePermit)>,
    room: Arc<Semaphore>,
    bound: u32,
}

/// The session went away.
#[derive(Debug)]
pub(crate) struct QueueClosed;

/// Room reserved in the queue for one packet.
#[derive(Debug)]
pub(crate) struct QueueSlot {
    tx: mpsc::UnboundedSender<(SourcePacket, OwnedSemaphorePermit)>,
    permit: OwnedSemaphorePermit,
}

impl PacketSender {
    /// Waits until the queue has room for a packet of `bytes` bytes.
    pub(crate) async fn reserve(&self, bytes: usize) -> Result<QueueSlot, QueueClosed> {
        let need = (bytes.min(self.bound as usize) as u32).max(1);
        let permit = self
            .room
            .clone()
            .acquire_many_owned(need)
            .await
            .map_err(|_| QueueClosed)?;
        Ok(QueueSlot {
            tx: self.tx.clone(),
            permit,
        })
    }

    /// Waits for room, then queues `packet`.
    pub(crate) async fn send(&self, packet: SourcePacket) -> Result<(), QueueClosed> {
        self.reserve(packet.data.len()).await?.send(packet)
    }
}

impl QueueSlot {
    /// Queues `packet` in the room reserved (freed when the session takes it).
    pub(crate) fn send(self, packet: SourcePacket) -> Result<(), QueueClosed> {
        self.tx.send((packet, self.permit)).map_err(|_| QueueClosed)
    }
}

impl Feed {
    /// Runs `task` (given the packet sender and the control receiver) on a thread named
    /// `name`, on `runtime`, with a queue of `queue_bytes` bytes of packets; `status` is what
    /// it reports.
    pub(crate) fn start<F>(
        name: &str,
        runtime: tokio::runtime::Runtime,
        queue_bytes: u64,
        status: Arc<Mutex<SourceStatus>>,
        task: impl FnOnce(PacketSender, mpsc::UnboundedReceiver<Control>) -> F + Send + 'static,
    ) -> Result<Feed, SourceError>
    where
        F: std::future::Future<Output = ()>,
    {
        let bound =
            queue_bytes.clamp(1, Semaphore::MAX_PERMITS.min(u32::MAX as usize) as u64) as u32;
        let room = Arc::new(Semaphore::new(bound as usize));
        let (tx, rx) = mpsc::unbounded_channel();
        let sender = PacketSender {
            tx,
            room: room.clone(),
            bound,
        };
        let (ctl, ctl_rx) = mpsc::unbounded_channel();
        let thread = std::thread::Builder::new()
            .name(name.into())
            .spawn(move || runtime.block_on(task(sender, ctl_rx)))
            .map_err(|e| SourceError::Thread(e.to_string()))?;
        Ok(Feed {
            rx,
            room,
            ctl: Some(ctl),
            status,
            thread: Some(thread),
            views_sent: 0,
        })
    }

    fn send(&self, c: Control) {
        if let Some(ctl) = &self.ctl {
            let _ = ctl.send(c);
        }
    }
}

impl PacketSource for Feed {
    fn try_next(&mut self) -> Option<SourcePacket> {
        // Dropping the permit gives the packet's room back.
        self.rx.try_recv().ok().map(|(packet, _room)| packet)
    }

    fn set_view(&mut self, spec: &ViewSpec) {
        self.views_sent += 1;
        self.send(Control::View(*spec));
    }

    fn dropped(&mut self, ids: Vec<u32>) {
        if !ids.is_empty() {
            self.send(Control::Dropped(ids));
        }
    }

    fn status(&self) -> SourceStatus {
        let mut s = self
            .status
            .lock()
            .map(|s| s.clone())
            .unwrap_or_else(|e| e.into_inner().clone());
        // Until the thread has applied the last view change, its `done` is about an earlier
        // view (a session that read it would stop with the new view unfinished).
        if s.views_applied < self.views_sent {
            s.done = false;
        }
        // Nor is it done while packets it delivered wait in the queue: the thread marks
        // `done` after queuing the last one (read after the status, so a `done` seen here
        // sees that packet), and a frame that found the queue empty a moment before would
        // otherwise take the view for converged with them untaken.
        if !self.rx.is_empty() {
            s.done = false;
        }
        s
    }
}

impl Drop for Feed {
    fn drop(&mut self) {
        // Closing the control channel ends the network task.
        self.ctl = None;
        self.room.close();
        self.rx.close();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl std::fmt::Debug for Control {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Control::View(_) => f.write_str("View"),
            Control::Dropped(ids) => write!(f, "Dropped({})", ids.len()),
        }
    }
}

/// [`PacketSource`] for a source whose packets come through its `feed` field (a [`Feed`]): each
/// call goes to the feed. The cache's and the range reader's sources are such wrappers.
macro_rules! packet_source_via_feed {
    ($source:ty) => {
        impl $crate::source::PacketSource for $source {
            fn try_next(&mut self) -> Option<$crate::source::SourcePacket> {
                $crate::source::PacketSource::try_next(&mut self.feed)
            }

            fn set_view(&mut self, spec: &::wavesplat_codec::view::ViewSpec) {
                $crate::source::PacketSource::set_view(&mut self.feed, spec);
            }

            fn dropped(&mut self, ids: Vec<u32>) {
                $crate::source::PacketSource::dropped(&mut self.feed, ids);
            }

            fn status(&self) -> $crate::source::SourceStatus {
                $crate::source::PacketSource::status(&self.feed)
            }
        }
    };
}
pub(crate) use packet_source_via_feed;

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;
    use wavesplat_codec::view::View;

    /// A feed whose thread has queued its last packet and said it is done is not done to the
    /// session until that packet is taken.
    #[test]
    fn a_feed_is_not_done_while_its_queue_holds_packets() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        let status = Arc::new(Mutex::new(SourceStatus::default()));
        let shared = status.clone();
        let (queued_tx, queued_rx) = std::sync::mpsc::channel();
        let mut feed = Feed::start("test-feed", runtime, 1 << 16, status, move |tx, mut ctl| {
            async move {
                let packet = SourcePacket {
                    id: 7,
                    data: vec![0; 16],
                    decoded: None,
                };
                if tx.send(packet).await.is_ok() {
                    shared.lock().expect("status").done = true;
                    let _ = queued_tx.send(());
                }
                // Runs until the feed is dropped.
                while ctl.recv().await.is_some() {}
            }
        })
        .expect("feed");
        queued_rx.recv().expect("the packet was queued");
        assert!(!feed.status().done, "done with a packet still queued");
        let p = feed.try_next().expect("the queued packet");
        assert_eq!(p.id, 7);
        assert!(feed.status().done);
    }

    /// A fed source is not done after a view change until its thread has applied it: a thread
    /// that said `done` for the old view and has not yet read the change must not end the new
    /// view (a render once stopped there with the new view unfinished, under load).
    #[test]
    fn a_view_change_is_not_done_before_the_thread_applies_it() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let status = Arc::new(Mutex::new(SourceStatus::default()));
        let (go_tx, go_rx) = std::sync::mpsc::channel::<()>();
        let shared = status.clone();
        let mut feed = Feed::start(
            "test-feed",
            runtime,
            1,
            status,
            move |_tx, mut ctl| async move {
                shared.lock().unwrap().done = true;
                // Hold the change back until the test says so, then apply it (done again).
                let _ = tokio::task::spawn_blocking(move || go_rx.recv()).await;
                if let Some(Control::View(_)) = ctl.recv().await {
                    let mut s = shared.lock().unwrap();
                    s.views_applied += 1;
                    s.done = true;
                }
                while ctl.recv().await.is_some() {}
            },
        )
        .unwrap();
        let until = |f: &Feed, done: bool| {
            for _ in 0..2000 {
                if f.status().done == done {
                    return true;
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            false
        };
        assert!(until(&feed, true), "the first view is done");
        feed.set_view(&ViewSpec::single(View::new(1.0, 0.5, 8, 8)));
        let early = feed.status().done;
        // Let the thread go before asserting, so that a failure does not leave it waiting.
        go_tx.send(()).unwrap();
        assert!(!early, "done before the change was applied");
        assert!(until(&feed, true), "the applied change is done");
    }
}
