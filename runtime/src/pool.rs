//! Recycled payload buffers. A big payload (a camera frame, an observation)
//! is written into a buffer an earlier one used, and the buffer comes back
//! when Zenoh and every reader have dropped the payload: no fresh
//! allocation, page faults or zero-fill per message. A receiver's decoded
//! observations come back the same way, through [`BufferPool::recycle`].

use std::sync::{Arc, Mutex, Weak};

use zenoh::bytes::ZBytes;

/// Idle buffers of one stream.
type Idle = Mutex<Vec<Vec<u8>>>;

/// A pool of buffers for one stream of same-sized payloads. Clones share
/// the pool.
#[derive(Debug, Clone, Default)]
pub struct BufferPool {
    idle: Arc<Idle>,
}

impl BufferPool {
    /// Idle buffers kept: a stream's payload is held by at most its
    /// reader's latest and the one in flight.
    pub const IDLE_MAX: usize = 4;

    /// An empty pool.
    pub fn new() -> Self {
        Self::default()
    }

    /// A buffer of `len` bytes. An idle one keeps its old bytes (the caller
    /// overwrites them all); a new one is zeroed.
    pub fn take(&self, len: usize) -> Vec<u8> {
        let mut buffer = self.idle_buffer().unwrap_or_default();
        buffer.resize(len, 0);
        buffer
    }

    /// An empty buffer for a caller that fills it by extending (a decoded
    /// observation): an idle one, its capacity kept, or a new one.
    pub fn take_empty(&self) -> Vec<u8> {
        let mut buffer = self.idle_buffer().unwrap_or_default();
        buffer.clear();
        buffer
    }

    /// Gives `buffer` back for a later take: a reader done with what it
    /// was handed (a decoded observation) saves the next one an allocation
    /// and its page faults.
    pub fn recycle(&self, buffer: Vec<u8>) {
        keep_idle(&self.idle, buffer);
    }

    fn idle_buffer(&self) -> Option<Vec<u8>> {
        self.idle.lock().ok().and_then(|mut idle| idle.pop())
    }

    /// `buffer` as a payload (not copied), back to the pool when dropped.
    pub fn payload(&self, buffer: Vec<u8>) -> ZBytes {
        bytes::Bytes::from_owner(Recycled {
            buffer,
            idle: Arc::downgrade(&self.idle),
        })
        .into()
    }

    /// Buffers waiting to be taken.
    pub fn idle(&self) -> usize {
        self.idle.lock().map_or(0, |idle| idle.len())
    }
}

/// A payload's buffer, back to its pool when the last holder drops it.
struct Recycled {
    buffer: Vec<u8>,
    idle: Weak<Idle>,
}

impl AsRef<[u8]> for Recycled {
    fn as_ref(&self) -> &[u8] {
        &self.buffer
    }
}

impl Drop for Recycled {
    fn drop(&mut self) {
        if let Some(pool) = self.idle.upgrade() {
            keep_idle(&pool, std::mem::take(&mut self.buffer));
        }
    }
}

/// Keeps `buffer` for a later take unless [`BufferPool::IDLE_MAX`] wait.
fn keep_idle(idle: &Idle, buffer: Vec<u8>) {
    if let Ok(mut idle) = idle.lock() {
        if idle.len() < BufferPool::IDLE_MAX {
            idle.push(buffer);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_buffer_comes_back_when_its_last_holder_drops_it() {
        let pool = BufferPool::new();
        let mut buffer = pool.take(8);
        assert_eq!(buffer, [0; 8], "new buffers are zeroed");
        buffer.copy_from_slice(b"observed");
        let address = buffer.as_ptr();
        let payload = pool.payload(buffer);
        assert_eq!(payload.to_bytes().as_ref(), b"observed", "not copied");
        let held = payload.clone();
        drop(payload);
        assert_eq!(pool.idle(), 0, "still held");
        let other = pool.take(8);
        assert_ne!(other.as_ptr(), address);
        drop(held);
        assert_eq!(pool.idle(), 1);
        let again = pool.take(8);
        assert_eq!(again.as_ptr(), address, "the same buffer");
        assert_eq!(again, b"observed", "old bytes kept, not zeroed");
        // Another length is resized to it.
        drop(pool.payload(again));
        assert_eq!(pool.take(3).len(), 3);
    }

    #[test]
    fn a_recycled_buffer_is_taken_again_empty() {
        let pool = BufferPool::new();
        let mut pixels = pool.take_empty();
        assert!(pixels.is_empty());
        pixels.extend_from_slice(&[7; 64]);
        let address = pixels.as_ptr();
        pool.recycle(pixels);
        let again = pool.take_empty();
        assert_eq!(again.as_ptr(), address, "the same allocation");
        assert!(again.is_empty(), "its bytes dropped");
        assert!(again.capacity() >= 64, "its capacity kept");
    }

    #[test]
    fn the_pool_keeps_at_most_its_limit_and_outlives_nothing() {
        let pool = BufferPool::new();
        let payloads: Vec<ZBytes> = (0..BufferPool::IDLE_MAX + 3)
            .map(|_| pool.payload(pool.take(16)))
            .collect();
        drop(payloads);
        assert_eq!(pool.idle(), BufferPool::IDLE_MAX);
        // Handed back by a reader: kept while fewer than the limit wait.
        let mut kept = pool.take_empty();
        kept.extend_from_slice(b"pixels");
        pool.recycle(kept);
        assert_eq!(pool.idle(), BufferPool::IDLE_MAX);
        // A payload outliving its pool is simply freed.
        let late = pool.payload(pool.take(16));
        drop(pool);
        drop(late);
    }
}
