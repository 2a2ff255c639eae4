//! What the AMX products share (`matvec::amx`'s integer products, `prompt_attention`'s bf16
//! ones): whether the CPU has the tiles and Linux lets this process use them, the tile
//! configuration (eight tiles of 16 rows of 64 bytes), and a 16 × 16 transpose of floats.

use std::arch::asm;
use std::arch::x86_64::*;
use std::sync::OnceLock;

/// Rows of a tile (and 32-bit values in a row).
pub const TILE_ROWS: usize = 16;
/// Bytes of a full tile (16 rows of 64 bytes).
pub const TILE_BYTES: usize = 1024;

/// Whether the CPU has AMX with 8-bit integer products and this process may use its tiles;
/// asked once.
pub fn int8_available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    // CPUID leaf 7, sub-leaf 0, EDX: bit 24 AMX-TILE, bit 25 AMX-INT8.
    *AVAILABLE.get_or_init(|| cpu_has(1 << 24 | 1 << 25) && tiles_granted())
}

/// Whether the CPU has AMX with bf16 products and this process may use its tiles; asked once.
pub fn bf16_available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    // CPUID leaf 7, sub-leaf 0, EDX: bit 22 AMX-BF16, bit 24 AMX-TILE.
    *AVAILABLE.get_or_init(|| cpu_has(1 << 22 | 1 << 24) && tiles_granted())
}

fn cpu_has(leaf7_edx_bits: u32) -> bool {
    __cpuid_count(7, 0).edx & leaf7_edx_bits == leaf7_edx_bits
}

/// Linux asks each process to request the tiles (`arch_prctl(ARCH_REQ_XCOMP_PERM)`); asked
/// once.
fn tiles_granted() -> bool {
    static GRANTED: OnceLock<bool> = OnceLock::new();
    *GRANTED.get_or_init(request_tiles)
}

#[cfg(target_os = "linux")]
fn request_tiles() -> bool {
    const SYS_ARCH_PRCTL: i64 = 158;
    const ARCH_REQ_XCOMP_PERM: i64 = 0x1023;
    const XFEATURE_XTILEDATA: i64 = 18;
    let result: i64;
    // SAFETY: the system call asks the kernel to let this process use the tile registers; it
    // reads and writes none of the program's memory, and clobbers only rax, rcx and r11.
    unsafe {
        asm!(
            "syscall",
            inlateout("rax") SYS_ARCH_PRCTL => result,
            in("rdi") ARCH_REQ_XCOMP_PERM,
            in("rsi") XFEATURE_XTILEDATA,
            lateout("rcx") _,
            lateout("r11") _,
            options(nostack),
        );
    }
    result == 0
}

#[cfg(not(target_os = "linux"))]
fn request_tiles() -> bool {
    false
}

/// The tile configuration `ldtilecfg` reads (64 bytes, palette 1).
#[derive(Default)]
#[repr(C, align(64))]
struct TileConfig {
    palette: u8,
    start_row: u8,
    reserved: [u8; 14],
    bytes_per_row: [u16; 16],
    rows: [u8; 16],
}

/// The tiles a thread uses for its part of a product, and the configuration they replace: a
/// thread of candle's pool that ran candle's own AMX kernel keeps that kernel's configuration
/// and expects it still there, so it is put back when done.
pub struct TilesInUse {
    previous: TileConfig,
}

impl TilesInUse {
    /// All eight 16 × 64 bytes.
    ///
    /// # Safety
    /// [`int8_available`] or [`bf16_available`] said yes (else the instructions fault).
    pub unsafe fn take() -> TilesInUse {
        let mut previous = TileConfig::default();
        let mut ours = TileConfig {
            palette: 1,
            ..TileConfig::default()
        };
        for t in 0..8 {
            ours.bytes_per_row[t] = 64;
            ours.rows[t] = TILE_ROWS as u8;
        }
        // SAFETY: both point at 64 bytes, aligned to 64 as the instructions ask; the CPU has
        // AMX (the caller's promise).
        unsafe {
            asm!("sttilecfg [{}]", in(reg) &mut previous, options(nostack));
            asm!("ldtilecfg [{}]", in(reg) &ours, options(nostack));
        }
        TilesInUse { previous }
    }
}

impl Drop for TilesInUse {
    fn drop(&mut self) {
        // SAFETY: only `take` makes a `TilesInUse`, on a CPU with AMX; `previous` is 64
        // bytes aligned to 64; a palette of 0 means no configuration was loaded before.
        unsafe {
            if self.previous.palette == 0 {
                asm!("tilerelease", options(nostack));
            } else {
                asm!("ldtilecfg [{}]", in(reg) &self.previous, options(nostack));
            }
        }
    }
}

/// The 16 × 16 transpose: lane `j` of row `i` to lane `i` of row `j`.
#[target_feature(enable = "avx512f")]
pub fn transpose(rows: [__m512; TILE_ROWS]) -> [__m512; TILE_ROWS] {
    // Pairs of rows interleaved by 32 then 64 bits: `quads[4g + j]`'s 128-bit lane `l` holds
    // column 4l + j of rows 4g..4g + 4.
    let pairs: [__m512; TILE_ROWS] = std::array::from_fn(|k| {
        let (a, b) = (rows[k & !1], rows[k | 1]);
        if k % 2 == 0 {
            _mm512_unpacklo_ps(a, b)
        } else {
            _mm512_unpackhi_ps(a, b)
        }
    });
    let quads: [__m512; TILE_ROWS] = std::array::from_fn(|k| {
        let (g, j) = (k / 4, k % 4);
        let a = _mm512_castps_pd(pairs[4 * g + j / 2]);
        let b = _mm512_castps_pd(pairs[4 * g + j / 2 + 2]);
        _mm512_castpd_ps(if j % 2 == 0 {
            _mm512_unpacklo_pd(a, b)
        } else {
            _mm512_unpackhi_pd(a, b)
        })
    });
    // Then the 128-bit lanes: column 4l + j is lane l of quads[j], [4 + j], [8 + j], [12 + j].
    let mut columns = [_mm512_setzero_ps(); TILE_ROWS];
    for j in 0..4 {
        let (a, b, c, d) = (quads[j], quads[4 + j], quads[8 + j], quads[12 + j]);
        let ab_low = _mm512_shuffle_f32x4::<0x44>(a, b);
        let ab_high = _mm512_shuffle_f32x4::<0xEE>(a, b);
        let cd_low = _mm512_shuffle_f32x4::<0x44>(c, d);
        let cd_high = _mm512_shuffle_f32x4::<0xEE>(c, d);
        columns[j] = _mm512_shuffle_f32x4::<0x88>(ab_low, cd_low);
        columns[4 + j] = _mm512_shuffle_f32x4::<0xDD>(ab_low, cd_low);
        columns[8 + j] = _mm512_shuffle_f32x4::<0x88>(ab_high, cd_high);
        columns[12 + j] = _mm512_shuffle_f32x4::<0xDD>(ab_high, cd_high);
    }
    columns
}
