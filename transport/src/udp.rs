//! Batched UDP I/O for the driver: many datagrams per system call each way.
//!
//! Sending, datagrams are encoded and sealed straight into one [`Outbox`] buffer; consecutive
//! datagrams to the same address leave in one `sendmsg` with UDP generic segmentation offload
//! (GSO: the kernel cuts the buffer into datagrams of `segment_size`, only the last may be
//! shorter). Receiving, one `recvmmsg` fills several buffers, and with generic receive offload
//! (GRO) each buffer may hold many datagrams of one sender at a fixed stride. Both come from
//! `quinn-udp` (quinn's socket layer, which probes GSO and GRO and falls back to one datagram
//! per call where the kernel or the network card refuses them).
//!
//! Every datagram keeps laminar's 5-byte header of an unreliable packet, so a node on this
//! path and a node on laminar's own (`batched_io = false`) understand each other.

use std::io::{self, IoSliceMut};
use std::net::SocketAddr;

use quinn_udp::{RecvMeta, Transmit, UdpSocketState};

/// Largest UDP payload of one `sendmsg` (IPv4's limit, less its headers).
const MAX_SEND_BYTES: usize = 65_000;
/// Receive buffers filled by one `recvmmsg`.
pub(crate) const RECV_BUFFERS: usize = 16;
/// Bytes of each receive buffer: room for a whole GRO train.
const RECV_BUFFER_BYTES: usize = 1 << 16;

/// Laminar's header of an unreliable packet: its protocol version's CRC-16 (big-endian), then
/// packet type `Packet`, delivery `Unreliable`, ordering `None` (all 0).
pub(crate) fn laminar_unreliable_header() -> [u8; 5] {
    let v = crc::crc16::checksum_x25(b"laminar-0.1.0").to_be_bytes();
    [v[0], v[1], 0, 0, 0]
}

/// What a flush achieved.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Flushed {
    /// System calls made.
    pub calls: u64,
    /// Datagrams the kernel took.
    pub datagrams: u64,
    /// Datagrams dropped on an error other than a full socket buffer.
    pub errors: u64,
}

/// Datagrams waiting for the socket, contiguous in one buffer, in the order they were made.
pub(crate) struct Outbox {
    buf: Vec<u8>,
    /// (destination, start, length) of each datagram, header included.
    items: Vec<(SocketAddr, usize, usize)>,
    /// Items before this one have left.
    next: usize,
    header: [u8; 5],
}

impl Default for Outbox {
    fn default() -> Self {
        Outbox {
            buf: Vec::with_capacity(1 << 17),
            items: Vec::with_capacity(256),
            next: 0,
            header: laminar_unreliable_header(),
        }
    }
}

impl Outbox {
    /// Datagrams not yet sent.
    pub(crate) fn len(&self) -> usize {
        self.items.len() - self.next
    }

    /// Starts a datagram: writes the header and returns the buffer to append the packet to,
    /// with the position to give [`Outbox::commit`] or [`Outbox::abort`].
    pub(crate) fn begin(&mut self) -> (usize, &mut Vec<u8>) {
        let start = self.buf.len();
        self.buf.extend_from_slice(&self.header);
        (start, &mut self.buf)
    }

    /// The datagram begun at `start` goes to `to`.
    pub(crate) fn commit(&mut self, to: SocketAddr, start: usize) {
        self.items.push((to, start, self.buf.len() - start));
    }

    /// Forgets the datagram begun at `start`.
    pub(crate) fn abort(&mut self, start: usize) {
        self.buf.truncate(start);
    }

    /// Takes the packet begun at `start` back out (without its header), for a caller that
    /// routes it elsewhere (an emulated link).
    pub(crate) fn take(&mut self, start: usize) -> Vec<u8> {
        let packet = self.buf[start + self.header.len()..].to_vec();
        self.buf.truncate(start);
        packet
    }

    /// Queues a finished packet (the header is added).
    pub(crate) fn push(&mut self, to: SocketAddr, packet: &[u8]) {
        let (start, buf) = self.begin();
        buf.extend_from_slice(packet);
        self.commit(to, start);
    }

    /// Sends what waits, with as few calls as GSO allows, through `send` (a socket, or a
    /// test's stand-in). Stops at the first `WouldBlock` and returns it; whatever was not
    /// taken stays queued, in order.
    pub(crate) fn flush(
        &mut self,
        max_segments: usize,
        mut send: impl FnMut(&Transmit<'_>) -> io::Result<()>,
    ) -> (Flushed, io::Result<()>) {
        let mut done = Flushed::default();
        let mut result = Ok(());
        while self.next < self.items.len() {
            let (to, start, seg) = self.items[self.next];
            let mut end = start + seg;
            let mut count = 1;
            // A train: same destination, every datagram `seg` bytes but the last, which may
            // be shorter (and then ends the train).
            while let Some(&(t, s, len)) = self.items.get(self.next + count) {
                if t != to
                    || count >= max_segments
                    || len > seg
                    || end - start + len > MAX_SEND_BYTES
                    || self.items[self.next + count - 1].2 != seg
                {
                    break;
                }
                debug_assert_eq!(s, end, "datagrams are contiguous");
                end += len;
                count += 1;
            }
            let transmit = Transmit {
                destination: to,
                ecn: None,
                contents: &self.buf[start..end],
                segment_size: (count > 1).then_some(seg),
                src_ip: None,
            };
            done.calls += 1;
            match send(&transmit) {
                Ok(()) => done.datagrams += count as u64,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    result = Err(e);
                    break;
                }
                Err(e) => {
                    // Unreachable or refused: like a loss on the way, which the endpoint
                    // recovers from.
                    tracing::debug!(%to, "send failed: {e}");
                    done.errors += count as u64;
                }
            }
            self.next += count;
        }
        if self.next == self.items.len() {
            self.items.clear();
            self.buf.clear();
            self.next = 0;
        }
        (done, result)
    }
}

/// Receive buffers and their metadata.
pub(crate) struct Inbox {
    bufs: Vec<Box<[u8]>>,
    meta: Vec<RecvMeta>,
    header: [u8; 5],
}

impl Default for Inbox {
    fn default() -> Self {
        Inbox {
            bufs: (0..RECV_BUFFERS)
                .map(|_| vec![0u8; RECV_BUFFER_BYTES].into_boxed_slice())
                .collect(),
            meta: vec![RecvMeta::default(); RECV_BUFFERS],
            header: laminar_unreliable_header(),
        }
    }
}

impl Inbox {
    /// One `recvmmsg`: calls `each(from, packet)` for every datagram that carries laminar's
    /// unreliable header (without the header) and counts the others in `filtered`. Returns
    /// the number of datagrams seen; `WouldBlock` when the socket was empty.
    pub(crate) fn recv(
        &mut self,
        state: &UdpSocketState,
        socket: &mio::net::UdpSocket,
        filtered: &mut u64,
        mut each: impl FnMut(SocketAddr, &mut [u8]),
    ) -> io::Result<usize> {
        let n = {
            let mut slices: [IoSliceMut<'_>; RECV_BUFFERS] = {
                let mut it = self.bufs.iter_mut();
                std::array::from_fn(|_| IoSliceMut::new(it.next().expect("RECV_BUFFERS")))
            };
            state.recv(socket.into(), &mut slices, &mut self.meta)?
        };
        let mut seen = 0;
        for (buf, meta) in self.bufs.iter_mut().zip(&self.meta).take(n) {
            let stride = meta.stride.max(1);
            for datagram in buf[..meta.len].chunks_mut(stride) {
                seen += 1;
                let h = self.header.len();
                if datagram.len() >= h && datagram[..h] == self.header {
                    each(meta.addr, &mut datagram[h..]);
                } else {
                    *filtered += 1;
                }
            }
        }
        Ok(seen)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn addr(port: u16) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], port))
    }

    /// (destination, datagram sizes) of each call.
    fn trains(outbox: &mut Outbox, max_segments: usize) -> Vec<(u16, Vec<usize>)> {
        let mut calls = Vec::new();
        let (_, r) = outbox.flush(max_segments, |t| {
            let sizes = match t.segment_size {
                None => vec![t.contents.len()],
                Some(s) => t.contents.chunks(s).map(|c| c.len()).collect(),
            };
            calls.push((t.destination.port(), sizes));
            Ok(())
        });
        r.unwrap();
        calls
    }

    #[test]
    fn equal_datagrams_to_one_address_leave_in_one_call_and_a_short_one_ends_the_train() {
        let mut o = Outbox::default();
        for len in [100, 100, 100, 40, 100] {
            o.push(addr(1), &vec![7; len]);
        }
        o.push(addr(2), &[1; 100]);
        assert_eq!(
            trains(&mut o, 64),
            vec![(1, vec![105, 105, 105, 45]), (1, vec![105]), (2, vec![105])]
        );
        assert_eq!(o.len(), 0);
    }

    #[test]
    fn trains_respect_the_segment_limit_and_the_size_of_one_call() {
        let mut o = Outbox::default();
        for _ in 0..10 {
            o.push(addr(1), &[0; 95]);
        }
        let calls = trains(&mut o, 4);
        assert_eq!(
            calls.iter().map(|c| c.1.len()).collect::<Vec<_>>(),
            vec![4, 4, 2]
        );
        for _ in 0..100 {
            o.push(addr(1), &[0; 1195]);
        }
        let calls = trains(&mut o, 64);
        assert!(
            calls
                .iter()
                .all(|c| c.1.iter().sum::<usize>() <= MAX_SEND_BYTES)
        );
        assert_eq!(calls.iter().map(|c| c.1.len()).sum::<usize>(), 100);
    }

    #[test]
    fn a_full_socket_keeps_the_rest_in_order_and_nothing_is_lost() {
        let mut o = Outbox::default();
        for i in 0..6u8 {
            o.push(addr(1 + (i as u16 % 2)), &[i; 10]);
        }
        let mut taken = Vec::new();
        let (done, r) = o.flush(64, |t| {
            if taken.len() == 3 {
                return Err(io::ErrorKind::WouldBlock.into());
            }
            taken.push(t.contents[5]);
            Ok(())
        });
        assert_eq!(r.unwrap_err().kind(), io::ErrorKind::WouldBlock);
        assert_eq!((done.datagrams, o.len()), (3, 3));
        // More queued behind the blocked ones goes after them.
        o.push(addr(1), &[9; 10]);
        let (_, r) = o.flush(64, |t| {
            taken.push(t.contents[5]);
            Ok(())
        });
        r.unwrap();
        assert_eq!(taken, vec![0, 1, 2, 3, 4, 5, 9]);
    }

    #[test]
    fn a_datagram_taken_back_or_aborted_leaves_no_trace() {
        let mut o = Outbox::default();
        let (s, buf) = o.begin();
        buf.extend_from_slice(b"abc");
        assert_eq!(o.take(s), b"abc");
        let (s, buf) = o.begin();
        buf.extend_from_slice(b"xyz");
        o.abort(s);
        o.push(addr(1), b"ok");
        let calls = trains(&mut o, 64);
        assert_eq!(calls, vec![(1, vec![7])]);
    }

    #[test]
    fn batched_sockets_carry_trains_both_ways_and_filter_foreign_datagrams() {
        let bind = || {
            let s = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
            s.set_nonblocking(true).unwrap();
            let s = mio::net::UdpSocket::from_std(s);
            let state = UdpSocketState::new((&s).into()).unwrap();
            (s, state)
        };
        let (tx, tx_state) = bind();
        let (rx, rx_state) = bind();
        let to = rx.local_addr().unwrap();
        let mut o = Outbox::default();
        let sent: Vec<Vec<u8>> = (0..200u32)
            .map(|i| {
                let len = if i % 50 == 49 { 300 } else { 1000 };
                (0..len).map(|k| (k as u32 ^ i) as u8).collect()
            })
            .collect();
        for p in &sent {
            o.push(to, p);
        }
        let (done, r) = o.flush(tx_state.max_gso_segments(), |t| {
            tx_state.try_send((&tx).into(), t)
        });
        r.unwrap();
        assert_eq!(done.datagrams, 200);
        // A datagram without laminar's header is filtered.
        let plain = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        plain.send_to(b"hello", to).unwrap();
        let mut inbox = Inbox::default();
        let (mut got, mut filtered) = (Vec::new(), 0);
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while got.len() < 200 || filtered == 0 {
            assert!(std::time::Instant::now() < deadline, "got {}", got.len());
            match inbox.recv(&rx_state, &rx, &mut filtered, |from, d| {
                assert_eq!(from.ip(), to.ip());
                got.push(d.to_vec());
            }) {
                Ok(_) => {}
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    std::thread::sleep(std::time::Duration::from_millis(1))
                }
                Err(e) => panic!("{e}"),
            }
        }
        assert_eq!(got, sent);
        assert_eq!(filtered, 1);
    }
}
