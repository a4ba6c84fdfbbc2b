//! Seal and open speed of the packet ciphers on 1,200-byte packets (one core).
use std::time::Instant;

use aes_gcm::Aes256Gcm;
use chacha20poly1305::ChaCha20Poly1305;
use chacha20poly1305::aead::{AeadInOut, KeyInit};

fn run<C: AeadInOut + KeyInit>(name: &str, encrypt: bool) {
    let c = C::new(&Default::default());
    let mut buf = vec![7u8; 1200];
    let n = 200_000;
    let t = Instant::now();
    let mut x = 0u8;
    for i in 0..n as u64 {
        let mut nonce = aes_gcm::aead::Nonce::<C>::default();
        nonce[..8].copy_from_slice(&i.to_le_bytes());
        let tag = if encrypt {
            let (header, body) = buf.split_at_mut(20);
            c.encrypt_inout_detached(&nonce, header, body.into())
        } else {
            c.encrypt_inout_detached(&nonce, &buf, (&mut [][..]).into())
        }
        .unwrap();
        x ^= tag[0];
    }
    let s = t.elapsed().as_secs_f64();
    println!(
        "{name} {}: {:.0} ns/packet, {:.2} GB/s ({x})",
        if encrypt { "encrypt" } else { "auth only" },
        s / n as f64 * 1e9,
        n as f64 * 1200.0 / s / 1e9
    );
}

fn main() {
    for e in [true, false] {
        run::<ChaCha20Poly1305>("chacha20-poly1305", e);
        run::<Aes256Gcm>("aes-256-gcm", e);
    }
}
