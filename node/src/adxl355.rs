//! The Analog Devices ADXL355, a low-noise three-axis MEMS accelerometer with a 20-bit output
//! and a 96-entry FIFO, read through a [`Bus`] (register reads and writes): Linux spidev in
//! [`crate::spidev`], a register model of the part in [`SimAdxl355`] for the tests.
//!
//! Register map and encodings from the ADXL354/ADXL355 data sheet (Rev. D): identification at
//! 0x00–0x02, `FIFO_ENTRIES` 0x05, `TEMP2`/`TEMP1` 0x06–0x07, `XDATA3`…`ZDATA1` 0x08–0x10,
//! `FIFO_DATA` 0x11, `FILTER` 0x28, `RANGE` 0x2C, `POWER_CTL` 0x2D, `RESET` 0x2F. A value is
//! 20-bit two's complement, left-justified over three registers (`DATA3` bits 19–12, `DATA2`
//! bits 11–4, `DATA1` bits 7–4 the lowest nibble); in the FIFO, bit 0 of `DATA1` marks an x
//! entry and bit 1 an empty FIFO.

use std::collections::VecDeque;

use crate::source::{now_ns, Sample, Source, SourceError};

pub const REG_DEVID_AD: u8 = 0x00;
pub const REG_DEVID_MST: u8 = 0x01;
pub const REG_PARTID: u8 = 0x02;
pub const REG_REVID: u8 = 0x03;
pub const REG_STATUS: u8 = 0x04;
pub const REG_FIFO_ENTRIES: u8 = 0x05;
pub const REG_TEMP2: u8 = 0x06;
pub const REG_XDATA3: u8 = 0x08;
pub const REG_FIFO_DATA: u8 = 0x11;
pub const REG_FILTER: u8 = 0x28;
pub const REG_FIFO_SAMPLES: u8 = 0x29;
pub const REG_RANGE: u8 = 0x2C;
pub const REG_POWER_CTL: u8 = 0x2D;
pub const REG_RESET: u8 = 0x2F;

pub const DEVID_AD: u8 = 0xAD;
pub const DEVID_MST: u8 = 0x1D;
pub const PARTID: u8 = 0xED;
/// Written to `RESET`, restarts the part as at power-on.
pub const RESET_CODE: u8 = 0x52;
/// `STATUS` bit: the FIFO overran and lost samples.
pub const STATUS_FIFO_OVR: u8 = 1 << 2;
/// `POWER_CTL` bit: standby (no measurement); set at power-on.
pub const POWER_STANDBY: u8 = 1 << 0;
/// Entries the FIFO holds (32 samples of three axes).
pub const FIFO_ENTRIES: usize = 96;

/// Output data rates the part offers, Hz, by the `ODR_LPF` code of `FILTER` (0 to 10).
pub const ODR_HZ: [f64; 11] = [
    4000.0, 2000.0, 1000.0, 500.0, 250.0, 125.0, 62.5, 31.25, 15.625, 7.8125, 3.90625,
];

/// Temperature transfer: 1885 LSB at 25 °C, −9.05 LSB/°C (nominal; the data sheet's intercept
/// varies from part to part, so this is a monitor, not a thermometer).
const TEMP_LSB_AT_25C: f64 = 1885.0;
const TEMP_LSB_PER_C: f64 = -9.05;

/// A register interface to the part.
pub trait Bus: Send {
    /// Reads `buf.len()` bytes from `reg` on. The part auto-increments the address, except on
    /// `FIFO_DATA`, where each three bytes pop one entry.
    fn read(&mut self, reg: u8, buf: &mut [u8]) -> Result<(), BusError>;
    /// Writes one register.
    fn write(&mut self, reg: u8, value: u8) -> Result<(), BusError>;
}

#[derive(Debug, thiserror::Error)]
#[error("{what}: {source}")]
pub struct BusError {
    pub what: String,
    #[source]
    pub source: std::io::Error,
}

#[derive(Debug, thiserror::Error)]
pub enum Adxl355Error {
    #[error("ADXL355 bus: {0}")]
    Bus(#[from] BusError),
    #[error(
        "not an ADXL355: identification reads {ad:#04x} {mst:#04x} {part:#04x}, expected 0xad 0x1d 0xed \
         (check wiring, chip select and SPI mode 0)"
    )]
    NotAnAdxl355 { ad: u8, mst: u8, part: u8 },
    #[error(
        "the ADXL355 cannot sample at {rate_hz} Hz: its output data rates are 4000, 2000, 1000, 500, \
         250, 125, 62.5, 31.25, 15.625, 7.8125 and 3.90625 Hz"
    )]
    Rate { rate_hz: f64 },
}

/// Measurement range, as the `RANGE` register's bits 1–0 encode it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Range {
    G2 = 1,
    G4 = 2,
    G8 = 3,
}

impl Range {
    /// Sensitivity, LSB per g (data sheet: 256 000, 128 000, 64 000).
    pub fn lsb_per_g(self) -> f64 {
        match self {
            Range::G2 => 256_000.0,
            Range::G4 => 128_000.0,
            Range::G8 => 64_000.0,
        }
    }

    fn from_bits(bits: u8) -> Range {
        match bits & 0b11 {
            2 => Range::G4,
            3 => Range::G8,
            // 0 is reserved; the part treats it as ±2 g, and so do we.
            _ => Range::G2,
        }
    }
}

/// The `ODR_LPF` code of a rate the part offers.
pub fn odr_code(rate_hz: f64) -> Result<u8, Adxl355Error> {
    ODR_HZ
        .iter()
        .position(|&r| r == rate_hz)
        .map(|i| i as u8)
        .ok_or(Adxl355Error::Rate { rate_hz })
}

/// A 20-bit two's-complement value from its three left-justified bytes (`DATA3`, `DATA2`,
/// `DATA1`); the low nibble of `DATA1` (FIFO markers) is not part of it.
pub fn decode_20bit(b: [u8; 3]) -> i32 {
    let raw = (u32::from(b[0]) << 12) | (u32::from(b[1]) << 4) | (u32::from(b[2]) >> 4);
    // Sign-extend from bit 19 by moving it to bit 31 and back.
    ((raw << 12) as i32) >> 12
}

/// The three bytes of a 20-bit value (`-524288..=524287`), markers clear.
pub fn encode_20bit(v: i32) -> [u8; 3] {
    let raw = (v as u32) & 0xF_FFFF;
    [
        (raw >> 12) as u8,
        (raw >> 4) as u8,
        ((raw & 0xF) << 4) as u8,
    ]
}

/// The part, configured and measuring.
pub struct Adxl355<B: Bus> {
    bus: B,
    range: Range,
    rate_hz: f64,
    /// Entries read from the FIFO but not yet a whole x, y, z sample.
    pending: Vec<i32>,
    fifo_buf: Vec<u8>,
    overruns: u64,
}

impl<B: Bus> Adxl355<B> {
    /// Checks the part's identity, resets it, sets range and rate, and starts measuring.
    pub fn open(mut bus: B, range: Range, rate_hz: f64) -> Result<Adxl355<B>, Adxl355Error> {
        let code = odr_code(rate_hz)?;
        let mut id = [0u8; 3];
        bus.read(REG_DEVID_AD, &mut id)?;
        if id != [DEVID_AD, DEVID_MST, PARTID] {
            return Err(Adxl355Error::NotAnAdxl355 {
                ad: id[0],
                mst: id[1],
                part: id[2],
            });
        }
        bus.write(REG_RESET, RESET_CODE)?;
        // Ranges and filters are written in standby, as the data sheet asks.
        bus.write(REG_POWER_CTL, POWER_STANDBY)?;
        let mut r = [0u8];
        bus.read(REG_RANGE, &mut r)?;
        // Keep the interrupt polarity and I2C speed bits as they are.
        bus.write(REG_RANGE, (r[0] & !0b11) | range as u8)?;
        // High-pass off (bits 6–4 zero): a node must see gravity and tilt.
        bus.write(REG_FILTER, code)?;
        bus.write(REG_POWER_CTL, 0)?;
        Ok(Adxl355 {
            bus,
            range,
            rate_hz,
            pending: Vec::with_capacity(3),
            fifo_buf: Vec::with_capacity(FIFO_ENTRIES * 3),
            overruns: 0,
        })
    }

    pub fn range(&self) -> Range {
        self.range
    }

    /// Times the FIFO overran (samples were lost) since opening.
    pub fn overruns(&self) -> u64 {
        self.overruns
    }

    /// Empties the FIFO into `out` as samples in g, oldest first; returns whether it had
    /// overrun since the last call (samples lost before the first of these).
    pub fn read_fifo(&mut self, out: &mut Vec<[f32; 3]>) -> Result<bool, Adxl355Error> {
        let mut status = [0u8; 2];
        // STATUS then FIFO_ENTRIES in one transfer; reading STATUS clears the overrun bit.
        self.bus.read(REG_STATUS, &mut status)?;
        let overran = status[0] & STATUS_FIFO_OVR != 0;
        if overran {
            self.overruns += 1;
            // Entries before the overrun belong to a sample whose axes may be gone.
            self.pending.clear();
        }
        let entries = usize::from(status[1] & 0x7F).min(FIFO_ENTRIES);
        if entries == 0 {
            return Ok(overran);
        }
        self.fifo_buf.resize(entries * 3, 0);
        self.bus.read(REG_FIFO_DATA, &mut self.fifo_buf)?;
        let scale = 1.0 / self.range.lsb_per_g();
        for e in self.fifo_buf.chunks_exact(3) {
            let low = e[2];
            if low & 0b10 != 0 {
                // The FIFO ran empty under the read.
                break;
            }
            let is_x = low & 0b01 != 0;
            if is_x {
                self.pending.clear();
            } else if self.pending.is_empty() {
                // A y or z entry without its x: the x was lost, skip to the next x.
                continue;
            }
            self.pending.push(decode_20bit([e[0], e[1], e[2]]));
            if self.pending.len() == 3 {
                let p = &self.pending;
                out.push([
                    (f64::from(p[0]) * scale) as f32,
                    (f64::from(p[1]) * scale) as f32,
                    (f64::from(p[2]) * scale) as f32,
                ]);
                self.pending.clear();
            }
        }
        Ok(overran)
    }

    /// The latest output registers (not the FIFO), in g.
    pub fn read_now(&mut self) -> Result<[f32; 3], Adxl355Error> {
        let mut b = [0u8; 9];
        self.bus.read(REG_XDATA3, &mut b)?;
        let scale = 1.0 / self.range.lsb_per_g();
        Ok([0, 1, 2].map(|i| {
            (f64::from(decode_20bit([b[3 * i], b[3 * i + 1], b[3 * i + 2]])) * scale) as f32
        }))
    }

    /// The part's temperature, °C (nominal transfer function).
    pub fn temperature_c(&mut self) -> Result<f32, Adxl355Error> {
        let mut b = [0u8; 2];
        self.bus.read(REG_TEMP2, &mut b)?;
        let raw = (u16::from(b[0] & 0x0F) << 8) | u16::from(b[1]);
        Ok((25.0 + (f64::from(raw) - TEMP_LSB_AT_25C) / TEMP_LSB_PER_C) as f32)
    }

    pub fn rate_hz(&self) -> f64 {
        self.rate_hz
    }
}

/// How often the FIFO is emptied: at 32 samples of room it lasts 0.32 s at 100 Hz; polling
/// every 50 ms keeps it under a quarter full at 125 Hz and wakes the node 20 times a second.
const POLL_S: f64 = 0.05;

/// The part as a [`Source`]: polls the FIFO and stamps its samples.
///
/// The newest sample in the FIFO was taken within the last output period before the read: it
/// is stamped half a period before the read's time, and the others a period apart before it.
/// That quantisation, uniform over a period, is the source's stamp uncertainty (period / √12),
/// on top of the clock's.
pub struct Adxl355Source<B: Bus> {
    part: Adxl355<B>,
    period_ns: f64,
    buf: Vec<[f32; 3]>,
    /// Whether to sleep between polls (off in tests, where the bus is simulated).
    pace: bool,
}

impl<B: Bus> Adxl355Source<B> {
    pub fn new(part: Adxl355<B>) -> Adxl355Source<B> {
        let period_ns = 1e9 / part.rate_hz();
        Adxl355Source {
            part,
            period_ns,
            buf: Vec::with_capacity(FIFO_ENTRIES / 3),
            pace: true,
        }
    }

    /// A source that does not sleep between polls, for a simulated bus.
    pub fn unpaced(part: Adxl355<B>) -> Adxl355Source<B> {
        Adxl355Source {
            pace: false,
            ..Self::new(part)
        }
    }

    pub fn part(&mut self) -> &mut Adxl355<B> {
        &mut self.part
    }
}

impl<B: Bus> Source for Adxl355Source<B> {
    fn rate_hz(&self) -> f64 {
        self.part.rate_hz()
    }

    fn read(&mut self, out: &mut Vec<Sample>) -> Result<(), SourceError> {
        loop {
            if self.pace {
                std::thread::sleep(std::time::Duration::from_secs_f64(POLL_S));
            }
            self.buf.clear();
            let overran = self.part.read_fifo(&mut self.buf)?;
            if overran {
                tracing::warn!(
                    overruns = self.part.overruns(),
                    "ADXL355 FIFO overran: samples lost"
                );
            }
            let read_ns = now_ns();
            let n = self.buf.len();
            if n == 0 {
                if self.pace {
                    continue;
                }
                return Ok(());
            }
            for (i, v) in self.buf.iter().enumerate() {
                let back = (n - 1 - i) as f64 + 0.5;
                out.push(Sample {
                    timestamp_ns: read_ns - (back * self.period_ns).round() as i64,
                    v: *v,
                });
            }
            return Ok(());
        }
    }

    fn temperature_c(&mut self) -> Option<f32> {
        match self.part.temperature_c() {
            Ok(t) => Some(t),
            Err(e) => {
                tracing::warn!(cause = %e, "ADXL355 temperature unreadable");
                None
            }
        }
    }

    fn stamp_uncertainty_ns(&self) -> f64 {
        self.period_ns / 12f64.sqrt()
    }
}

/// A register model of the ADXL355, as a [`Bus`]: identification, reset, range, filter and
/// power registers, the output registers, the temperature and the 96-entry FIFO with its
/// x markers, empty indicator and overrun bit. Measurements are pushed in g and encoded at
/// the range the registers are set to, as the part would.
#[derive(Debug, Clone)]
pub struct SimAdxl355 {
    regs: [u8; 0x30],
    fifo: VecDeque<[u8; 3]>,
    overrun: bool,
    /// Every register write, in order, for tests of the configuration sequence.
    pub writes: Vec<(u8, u8)>,
}

impl Default for SimAdxl355 {
    fn default() -> Self {
        Self::new()
    }
}

impl SimAdxl355 {
    pub fn new() -> SimAdxl355 {
        let mut s = SimAdxl355 {
            regs: [0; 0x30],
            fifo: VecDeque::with_capacity(FIFO_ENTRIES),
            overrun: false,
            writes: Vec::new(),
        };
        s.power_on();
        s
    }

    fn power_on(&mut self) {
        self.regs = [0; 0x30];
        self.regs[REG_DEVID_AD as usize] = DEVID_AD;
        self.regs[REG_DEVID_MST as usize] = DEVID_MST;
        self.regs[REG_PARTID as usize] = PARTID;
        self.regs[REG_REVID as usize] = 0x01;
        // Reset values from the data sheet: ODR 4 kHz, FIFO watermark 0x60, ±2 g with active
        // high interrupts, standby.
        self.regs[REG_FILTER as usize] = 0x00;
        self.regs[REG_FIFO_SAMPLES as usize] = 0x60;
        self.regs[REG_RANGE as usize] = 0x81;
        self.regs[REG_POWER_CTL as usize] = POWER_STANDBY;
        self.set_temperature_c(25.0);
        self.fifo.clear();
        self.overrun = false;
    }

    pub fn range(&self) -> Range {
        Range::from_bits(self.regs[REG_RANGE as usize])
    }

    pub fn odr_hz(&self) -> f64 {
        ODR_HZ[usize::from(self.regs[REG_FILTER as usize] & 0x0F).min(ODR_HZ.len() - 1)]
    }

    pub fn measuring(&self) -> bool {
        self.regs[REG_POWER_CTL as usize] & POWER_STANDBY == 0
    }

    pub fn set_temperature_c(&mut self, t_c: f64) {
        let raw = (TEMP_LSB_AT_25C + (t_c - 25.0) * TEMP_LSB_PER_C).round() as u16 & 0x0FFF;
        self.regs[REG_TEMP2 as usize] = (raw >> 8) as u8;
        self.regs[REG_TEMP2 as usize + 1] = raw as u8;
    }

    /// Pushes one raw sample (20-bit counts per axis) into the output registers and the FIFO,
    /// as the part does at each output period while measuring.
    pub fn push_raw(&mut self, v: [i32; 3]) {
        if !self.measuring() {
            return;
        }
        for (axis, &x) in v.iter().enumerate() {
            let b = encode_20bit(x);
            let at = REG_XDATA3 as usize + 3 * axis;
            self.regs[at..at + 3].copy_from_slice(&b);
        }
        if self.fifo.len() + 3 > FIFO_ENTRIES {
            // A full FIFO keeps what it has and drops the new sample.
            self.overrun = true;
            return;
        }
        for (axis, &x) in v.iter().enumerate() {
            let mut b = encode_20bit(x);
            if axis == 0 {
                b[2] |= 0b01;
            }
            self.fifo.push_back(b);
        }
    }

    /// Pushes a sample in g, quantised and clipped at the configured range.
    pub fn push_g(&mut self, g: [f64; 3]) {
        let lsb = self.range().lsb_per_g();
        self.push_raw(g.map(|x| ((x * lsb).round() as i64).clamp(-524_288, 524_287) as i32));
    }

    /// Drops the first FIFO entry, as a lost read would, leaving the FIFO out of step.
    pub fn drop_fifo_entry(&mut self) {
        self.fifo.pop_front();
    }

    pub fn fifo_len(&self) -> usize {
        self.fifo.len()
    }

    fn status(&self) -> u8 {
        let mut s = 0;
        if !self.fifo.is_empty() {
            s |= 1;
        }
        if self.fifo.len() >= FIFO_ENTRIES {
            s |= 1 << 1;
        }
        if self.overrun {
            s |= STATUS_FIFO_OVR;
        }
        s
    }

    fn read_one(&mut self, reg: u8) -> u8 {
        match reg {
            REG_STATUS => {
                let s = self.status();
                self.overrun = false;
                s
            }
            REG_FIFO_ENTRIES => self.fifo.len() as u8,
            r if (r as usize) < self.regs.len() => self.regs[r as usize],
            _ => 0,
        }
    }
}

impl Bus for SimAdxl355 {
    fn read(&mut self, reg: u8, buf: &mut [u8]) -> Result<(), BusError> {
        if reg == REG_FIFO_DATA {
            for chunk in buf.chunks_mut(3) {
                // An empty FIFO reads as an entry with the empty bit set.
                let e = self.fifo.pop_front().unwrap_or([0, 0, 0b10]);
                chunk.copy_from_slice(&e[..chunk.len()]);
            }
            return Ok(());
        }
        for (i, b) in buf.iter_mut().enumerate() {
            *b = self.read_one(reg.wrapping_add(i as u8));
        }
        Ok(())
    }

    fn write(&mut self, reg: u8, value: u8) -> Result<(), BusError> {
        self.writes.push((reg, value));
        match reg {
            REG_RESET if value == RESET_CODE => self.power_on(),
            REG_FILTER
            | REG_FIFO_SAMPLES
            | REG_RANGE
            | REG_POWER_CTL
            | 0x1E..=0x27
            | 0x2A
            | 0x2B
            | 0x2E => self.regs[reg as usize] = value,
            // Read-only and reserved registers ignore writes, as the part does.
            _ => {}
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn twenty_bit_values_decode_with_their_sign() {
        for v in [0, 1, -1, 524_287, -524_288, 256_000, -128_000, 12_345] {
            assert_eq!(decode_20bit(encode_20bit(v)), v, "{v}");
        }
        // The data sheet's layout, by hand: 0x7FFFF is the largest, 0x80000 the smallest.
        assert_eq!(decode_20bit([0x7F, 0xFF, 0xF0]), 524_287);
        assert_eq!(decode_20bit([0x80, 0x00, 0x00]), -524_288);
        assert_eq!(decode_20bit([0xFF, 0xFF, 0xF0]), -1);
        // FIFO markers in the low nibble are not part of the value.
        assert_eq!(decode_20bit([0x00, 0x00, 0x13]), 1);
    }

    #[test]
    fn open_checks_identity_and_configures() {
        let part = Adxl355::open(SimAdxl355::new(), Range::G8, 125.0).unwrap();
        let bus = &part.bus;
        assert_eq!(bus.range(), Range::G8);
        assert_eq!(bus.odr_hz(), 125.0);
        assert!(bus.measuring());
        // Reset first, then the range and filter in standby, measurement last.
        let regs: Vec<u8> = bus.writes.iter().map(|w| w.0).collect();
        assert_eq!(
            regs,
            [
                REG_RESET,
                REG_POWER_CTL,
                REG_RANGE,
                REG_FILTER,
                REG_POWER_CTL
            ]
        );
        // The interrupt polarity bit of RANGE is kept.
        assert_eq!(bus.regs[REG_RANGE as usize], 0x83);

        let mut other = SimAdxl355::new();
        other.regs[REG_PARTID as usize] = 0xEC;
        let e = Adxl355::open(other, Range::G2, 125.0).err().unwrap();
        assert!(e.to_string().contains("0xec"), "{e}");

        let e = Adxl355::open(SimAdxl355::new(), Range::G2, 100.0)
            .err()
            .unwrap();
        assert!(e.to_string().contains("125, 62.5"), "{e}");
    }

    #[test]
    fn range_scales_counts_to_g() {
        for (range, lsb) in [
            (Range::G2, 256_000.0),
            (Range::G4, 128_000.0),
            (Range::G8, 64_000.0),
        ] {
            let mut part = Adxl355::open(SimAdxl355::new(), range, 125.0).unwrap();
            part.bus.push_g([1.5, -0.25, 1.0]);
            let mut out = Vec::new();
            part.read_fifo(&mut out).unwrap();
            assert_eq!(out.len(), 1);
            let want = [1.5, -0.25, 1.0].map(|g: f64| ((g * lsb).round() / lsb) as f32);
            assert_eq!(out[0], want, "{range:?}");
            assert_eq!(part.read_now().unwrap(), want);
        }
        // Beyond the range the part clips at the largest count.
        let mut part = Adxl355::open(SimAdxl355::new(), Range::G2, 125.0).unwrap();
        part.bus.push_g([3.0, -3.0, 0.0]);
        let mut out = Vec::new();
        part.read_fifo(&mut out).unwrap();
        assert_eq!(out[0][0], (524_287.0 / 256_000.0) as f32);
        assert_eq!(out[0][1], (-524_288.0 / 256_000.0) as f32);
    }

    #[test]
    fn fifo_reads_in_order_resyncs_on_x_and_reports_overruns() {
        let mut part = Adxl355::open(SimAdxl355::new(), Range::G2, 125.0).unwrap();
        for i in 0..5 {
            part.bus.push_raw([i, 100 + i, -i]);
        }
        let mut out = Vec::new();
        assert!(!part.read_fifo(&mut out).unwrap());
        let lsb = 256_000.0f64;
        let got: Vec<[i32; 3]> = out
            .iter()
            .map(|v| v.map(|x| (f64::from(x) * lsb).round() as i32))
            .collect();
        assert_eq!(
            got,
            (0..5).map(|i| [i, 100 + i, -i]).collect::<Vec<_>>(),
            "oldest first, axes in order"
        );
        assert_eq!(part.bus.fifo_len(), 0);

        // An entry lost: the sample whose x is gone is skipped, the next starts at its x.
        part.bus.push_raw([1, 2, 3]);
        part.bus.push_raw([4, 5, 6]);
        part.bus.drop_fifo_entry();
        out.clear();
        part.read_fifo(&mut out).unwrap();
        assert_eq!(out.len(), 1);
        assert_eq!(
            out[0].map(|x| (f64::from(x) * lsb).round() as i32),
            [4, 5, 6]
        );

        // Forty samples into a FIFO of 32: 32 kept, the overrun reported once.
        for i in 0..40 {
            part.bus.push_raw([i, i, i]);
        }
        out.clear();
        assert!(part.read_fifo(&mut out).unwrap());
        assert_eq!(out.len(), 32);
        assert_eq!(part.overruns(), 1);
        out.clear();
        assert!(
            !part.read_fifo(&mut out).unwrap(),
            "reading STATUS cleared it"
        );
        assert!(out.is_empty());
    }

    #[test]
    fn temperature_follows_the_nominal_transfer() {
        let mut part = Adxl355::open(SimAdxl355::new(), Range::G2, 125.0).unwrap();
        part.bus.set_temperature_c(40.0);
        let t = part.temperature_c().unwrap();
        assert!((t - 40.0).abs() < 0.1, "{t}");
    }

    #[test]
    fn the_source_stamps_the_newest_sample_within_a_period_of_the_read() {
        let part = Adxl355::open(SimAdxl355::new(), Range::G2, 125.0).unwrap();
        let mut src = Adxl355Source::unpaced(part);
        for _ in 0..10 {
            src.part().bus.push_g([0.0, 0.0, 1.0]);
        }
        let before = now_ns();
        let mut out = Vec::new();
        src.read(&mut out).unwrap();
        let after = now_ns();
        assert_eq!(out.len(), 10);
        for w in out.windows(2) {
            assert_eq!(w[1].timestamp_ns - w[0].timestamp_ns, 8_000_000);
        }
        let last = out[9].timestamp_ns;
        assert!(last >= before - 4_000_000 && last <= after - 4_000_000 + 1);
        assert_eq!(out[0].v, [0.0, 0.0, 1.0]);
        assert!(src.temperature_c().is_some());
    }
}
