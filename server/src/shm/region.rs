//! One session's region: an anonymous memfd (owner-only, no name in `/dev/shm`, sealed at its
//! size). The kernel frees it when the last descriptor and mapping go, so neither
//! side's death, `kill -9` included, can leave it behind.
//!
//! The client maps it; this side never does. It reads the actions with `pread` (and checks that
//! copy, as a Step checks its request) and writes the reply with `pwritev`: no pointer into
//! memory the client may change at any moment, no unsafe code, and nothing the client does to
//! the pages can fault this process.

use std::io::IoSlice;
use std::os::fd::{AsFd, BorrowedFd, OwnedFd};

use rustix::fs::{MemfdFlags, Mode, SealFlags};

use super::layout::{FIELDS, Layout, batch_arrays};
use crate::session::Batch;

/// Zeros for the padding between two arrays written in one `pwritev`.
static ZEROS: [u8; MAX_GAP] = [0; MAX_GAP];
/// Gaps up to this many bytes are written as zeros to keep one `pwritev`; a longer one (an
/// array this session's replies leave empty) starts another.
const MAX_GAP: usize = 512;

/// A memfd of one session's layout.
#[derive(Debug)]
pub struct Region {
    /// The memfd, passed to the client once and closed here when the region is dropped.
    fd: OwnedFd,
    /// Where each array lives.
    layout: Layout,
    /// Reused for the seeds and episode counts encoded as bytes.
    scratch: Vec<u8>,
}

impl Region {
    /// A region for `layout`, its header written.
    pub fn new(layout: Layout) -> std::io::Result<Region> {
        let fd = rustix::fs::memfd_create(
            "dinerdash-session",
            MemfdFlags::CLOEXEC | MemfdFlags::ALLOW_SEALING,
        )?;
        // Only this user may open it through /proc; a memfd has no other name.
        rustix::fs::fchmod(&fd, Mode::RUSR | Mode::WUSR)?;
        rustix::fs::ftruncate(&fd, layout.bytes as u64)?;
        // Fixed at its size: a client that shrank it would fault in its own mapping only, but
        // the layout must stay what the header says.
        rustix::fs::fcntl_add_seals(&fd, SealFlags::SHRINK | SealFlags::GROW | SealFlags::SEAL)?;
        let region = Region {
            fd,
            layout,
            scratch: Vec::new(),
        };
        write_all(&region.fd, &[IoSlice::new(&region.layout.header())], 0)?;
        Ok(region)
    }

    /// The memfd, to pass to the client.
    pub fn fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }

    /// The region's bytes (what the memory budget charges).
    pub fn bytes(&self) -> usize {
        self.layout.bytes
    }

    /// A copy of the actions the client wrote (N x int32), to be checked as a Step checks them.
    pub fn read_actions(&self, into: &mut Vec<u8>) -> std::io::Result<()> {
        let (offset, len) = self.layout.actions();
        into.resize(len, 0);
        let mut done = 0;
        while done < len {
            let n = rustix::io::pread(&self.fd, &mut into[done..], (offset + done) as u64)?;
            if n == 0 {
                return Err(std::io::ErrorKind::UnexpectedEof.into());
            }
            done += n;
        }
        Ok(())
    }

    /// Writes a Step's reply: the length of each array and the arrays, in as few `pwritev` as
    /// the arrays left empty allow (one, for a session of masks without SAME_STEP or expert),
    /// with the Batch's `drain_remaining_ms` after the lengths.
    pub fn write_batch(&mut self, batch: &Batch, drain_remaining_ms: u32) -> std::io::Result<()> {
        let mut scratch = std::mem::take(&mut self.scratch);
        let arrays = batch_arrays(batch, &mut scratch);
        let mut lengths = [0u8; 4 * FIELDS.len() + 4];
        for (i, array) in arrays.iter().enumerate() {
            let len = array.len().min(self.layout.arrays[i + 1].1) as u32;
            lengths[4 * (i + 1)..4 * (i + 2)].copy_from_slice(&len.to_le_bytes());
        }
        lengths[4 * FIELDS.len()..].copy_from_slice(&drain_remaining_ms.to_le_bytes());
        // The lengths table (the actions' entry, 0, included), drain_remaining_ms, then each
        // array.
        // At most the lengths, then a gap and an array for each array: no allocation a Step.
        let mut run = [IoSlice::new(&[]); 2 * FIELDS.len()];
        run[0] = IoSlice::new(&lengths);
        let mut used = 1;
        let mut start = Layout::length_at(0);
        let mut cursor = start + lengths.len();
        let mut result = Ok(());
        for (i, array) in arrays.iter().enumerate() {
            let (offset, capacity) = self.layout.arrays[i + 1];
            let data = &array[..array.len().min(capacity)];
            if data.is_empty() {
                continue;
            }
            let gap = offset - cursor;
            if gap <= MAX_GAP {
                run[used] = IoSlice::new(&ZEROS[..gap]);
                used += 1;
            } else {
                result = result.and(write_all(&self.fd, &run[..used], start as u64));
                used = 0;
                start = offset;
            }
            run[used] = IoSlice::new(data);
            used += 1;
            cursor = offset + data.len();
        }
        result = result.and(write_all(&self.fd, &run[..used], start as u64));
        self.scratch = scratch;
        result
    }
}

/// `pwritev` of all of `slices` at `offset` (a memfd takes them whole; a short write is an
/// error rather than a retry loop).
fn write_all(fd: &OwnedFd, slices: &[IoSlice<'_>], offset: u64) -> std::io::Result<()> {
    let total: usize = slices.iter().map(|s| s.len()).sum();
    let n = rustix::io::pwritev(fd, slices, offset)?;
    if n != total {
        return Err(std::io::Error::other(format!(
            "short write to the region: {n} of {total} bytes"
        )));
    }
    Ok(())
}
