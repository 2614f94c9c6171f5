//! The ADXL355's [`Bus`] over Linux spidev (`/dev/spidevB.C`): one full-duplex transfer per
//! register access through the `SPI_IOC_MESSAGE` ioctl, SPI mode 0, 8 bits a word.
//!
//! Thin and not exercised on hardware by the tests (they use [`crate::adxl355::SimAdxl355`]);
//! what can be checked without a bus, the command bytes, is ([`read_frame`], [`write_frame`]).

use std::fs::{File, OpenOptions};
use std::os::fd::AsRawFd;
use std::path::Path;

use crate::adxl355::{Bus, BusError};

/// The ADXL355 takes up to 10 MHz; 5 MHz leaves margin for wiring on a carrier board.
pub const DEFAULT_SPEED_HZ: u32 = 5_000_000;

/// `struct spi_ioc_transfer` of `<linux/spi/spidev.h>`.
#[repr(C)]
#[derive(Default)]
struct SpiIocTransfer {
    tx_buf: u64,
    rx_buf: u64,
    len: u32,
    speed_hz: u32,
    delay_usecs: u16,
    bits_per_word: u8,
    cs_change: u8,
    tx_nbits: u8,
    rx_nbits: u8,
    word_delay_usecs: u8,
    pad: u8,
}

const SPI_IOC_MAGIC: u64 = b'k' as u64;
const IOC_WRITE: u64 = 1;

/// `_IOW(SPI_IOC_MAGIC, nr, size)`.
const fn iow(nr: u64, size: u64) -> u64 {
    (IOC_WRITE << 30) | (size << 16) | (SPI_IOC_MAGIC << 8) | nr
}

/// `SPI_IOC_MESSAGE(1)`.
const SPI_IOC_MESSAGE_1: u64 = iow(0, std::mem::size_of::<SpiIocTransfer>() as u64);
/// `SPI_IOC_WR_MODE`.
const SPI_IOC_WR_MODE: u64 = iow(1, 1);
/// `SPI_IOC_WR_BITS_PER_WORD`.
const SPI_IOC_WR_BITS_PER_WORD: u64 = iow(3, 1);
/// `SPI_IOC_WR_MAX_SPEED_HZ`.
const SPI_IOC_WR_MAX_SPEED_HZ: u64 = iow(4, 4);

/// The command byte of a read of `reg`: the address in bits 7–1, bit 0 set for a read.
pub fn read_frame(reg: u8) -> u8 {
    (reg << 1) | 1
}

/// The two bytes of a write of `value` to `reg`.
pub fn write_frame(reg: u8, value: u8) -> [u8; 2] {
    [reg << 1, value]
}

/// An open spidev device.
pub struct SpiBus {
    file: File,
    path: String,
    speed_hz: u32,
    tx: Vec<u8>,
    rx: Vec<u8>,
}

impl SpiBus {
    pub fn open(path: &Path, speed_hz: u32) -> Result<SpiBus, BusError> {
        let name = path.display().to_string();
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .open(path)
            .map_err(|source| BusError {
                what: format!("cannot open {name}"),
                source,
            })?;
        let bus = SpiBus {
            file,
            path: name,
            speed_hz,
            tx: Vec::with_capacity(300),
            rx: Vec::with_capacity(300),
        };
        bus.set(SPI_IOC_WR_MODE, &0u8, "SPI mode 0")?;
        bus.set(SPI_IOC_WR_BITS_PER_WORD, &8u8, "8 bits per word")?;
        bus.set(SPI_IOC_WR_MAX_SPEED_HZ, &speed_hz, "SPI speed")?;
        Ok(bus)
    }

    fn set<T>(&self, request: u64, value: &T, what: &str) -> Result<(), BusError> {
        // SAFETY: the request's size matches `T` (u8 for mode and word size, u32 for the
        // speed), and the kernel only reads `*value`, which outlives the call.
        let r = unsafe {
            libc::ioctl(
                self.file.as_raw_fd(),
                request as libc::c_ulong,
                value as *const T,
            )
        };
        if r < 0 {
            return Err(BusError {
                what: format!("{}: cannot set {what}", self.path),
                source: std::io::Error::last_os_error(),
            });
        }
        Ok(())
    }

    /// One full-duplex transfer of `self.tx` into `self.rx`.
    fn transfer(&mut self) -> Result<(), BusError> {
        self.rx.clear();
        self.rx.resize(self.tx.len(), 0);
        let t = SpiIocTransfer {
            tx_buf: self.tx.as_ptr() as u64,
            rx_buf: self.rx.as_mut_ptr() as u64,
            // Transfers here are at most 1 + 96·3 bytes.
            len: self.tx.len() as u32,
            speed_hz: self.speed_hz,
            bits_per_word: 8,
            ..SpiIocTransfer::default()
        };
        // SAFETY: `t` points at `tx` and `rx`, both `len` bytes long and alive for the call;
        // the kernel reads `tx`, writes `rx` and reads `t`, nothing else.
        let r = unsafe {
            libc::ioctl(
                self.file.as_raw_fd(),
                SPI_IOC_MESSAGE_1 as libc::c_ulong,
                &t as *const SpiIocTransfer,
            )
        };
        if r < 0 {
            return Err(BusError {
                what: format!("{}: SPI transfer", self.path),
                source: std::io::Error::last_os_error(),
            });
        }
        Ok(())
    }
}

impl Bus for SpiBus {
    fn read(&mut self, reg: u8, buf: &mut [u8]) -> Result<(), BusError> {
        self.tx.clear();
        self.tx.push(read_frame(reg));
        self.tx.resize(1 + buf.len(), 0);
        self.transfer()?;
        buf.copy_from_slice(&self.rx[1..]);
        Ok(())
    }

    fn write(&mut self, reg: u8, value: u8) -> Result<(), BusError> {
        self.tx.clear();
        self.tx.extend_from_slice(&write_frame(reg, value));
        self.transfer()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_and_request_numbers_match_the_kernel_headers() {
        assert_eq!(read_frame(0x11), 0x23);
        assert_eq!(write_frame(0x2D, 0), [0x5A, 0]);
        assert_eq!(std::mem::size_of::<SpiIocTransfer>(), 32);
        // Values of the C macros on Linux (asm-generic ioctl layout).
        assert_eq!(SPI_IOC_MESSAGE_1, 0x4020_6B00);
        assert_eq!(SPI_IOC_WR_MODE, 0x4001_6B01);
        assert_eq!(SPI_IOC_WR_MAX_SPEED_HZ, 0x4004_6B04);
    }
}
