//! The paper's packet syntax (Table 3) and its two entropy coders. The coefficients are
//! grouped into runs of equal substream id (channel × band: type, depth and colour channel,
//! run-length coded); per coefficient the position as a signed delta from the previous
//! coefficient's position (mapped to this coefficient's level grid; clustering makes these
//! short), a sign bit, and the quantization step δ of its substream's chain ([`super::quant`]).
//! With [`CoderKind::Huffman`] the run tags, run lengths, position deltas and value steps are
//! coded with the four static tables of the header (magnitude categories + raw extra bits),
//! fitted to the file's symbols; with [`CoderKind::Range`] the same syntax elements go through
//! adaptive binary models that reset at every packet.

use super::coefficient::PacketFraming;
use super::coefficient::{Coefficient, PacketInput, SizeBreakdown, INITIAL_CAPACITY};
use super::quant::Chain;
use super::{invalid, CoderKind, FormatError, Header, HuffmanTables, CATEGORY_ALPHABET};
use crate::entropy::bits::{BitReader, BitSink, BitWriter};
use crate::entropy::category::{
    decode_signed, decode_unsigned, encode_signed, encode_unsigned, signed_category,
    unsigned_category,
};
use crate::entropy::huffman::{HuffmanCode, HuffmanDecoder};
use crate::entropy::range::{AdaptiveSintModel, AdaptiveUintModel, RangeDecoder, RangeEncoder};

/// Syntax elements of one coefficient, after quantization.
#[derive(Debug, Clone, Copy)]
struct Symbols {
    substream: usize,
    dpos: [i64; 3],
    negative: bool,
    step: i64,
}

/// Receives the syntax elements of a packet in coding order.
trait SyntaxSink {
    fn run(&mut self, substream: usize, length: u64);
    fn coefficient(&mut self, level: usize, band: usize, s: &Symbols);
}

/// Quantizes a packet and computes its syntax elements and reconstruction.
fn symbolize(header: &Header, input: &PacketInput) -> (Vec<Symbols>, Vec<Coefficient>) {
    let nsub = header.substream_count();
    let mut chains: Vec<Option<Chain>> = vec![None; nsub];
    let origin = header.tile_origin(input.tile);
    let mut prev_voxel = [0i64; 3];
    let mut syms = Vec::with_capacity(input.coefficients.len());
    let mut recon = Vec::with_capacity(input.coefficients.len());
    for c in &input.coefficients {
        let sub = header.substream_id(c.channel as usize, c.band);
        let params = header.substreams[sub].expect("substream of a coded coefficient has params");
        let chain = chains[sub].get_or_insert_with(|| {
            Chain::new(header.chain_start(sub, input.layer), params.delta as f64)
        });
        let (step, mag) = chain.encode((c.value as f64).abs());
        let level = c.band.level as u32;
        let mut dpos = [0i64; 3];
        for a in 0..3 {
            let local = c.pos[a] as i64 - (origin[a] >> level) as i64;
            dpos[a] = local - (prev_voxel[a] >> level);
            prev_voxel[a] = local << level;
        }
        let negative = c.value < 0.0;
        syms.push(Symbols {
            substream: sub,
            dpos,
            negative,
            step,
        });
        let v = if negative { -mag } else { mag } as f32;
        recon.push(Coefficient { value: v, ..*c });
    }
    (syms, recon)
}

/// Feeds a packet's symbols, grouped in runs, to a sink.
fn emit(header: &Header, syms: &[Symbols], sink: &mut impl SyntaxSink) {
    let nb = header.geometry.band_count();
    let bands = header.geometry.bands();
    let mut i = 0;
    while i < syms.len() {
        let s = syms[i].substream;
        let mut j = i;
        while j < syms.len() && syms[j].substream == s {
            j += 1;
        }
        sink.run(s, (j - i) as u64);
        let band_index = s % nb;
        let level = bands[band_index].level as usize;
        for sym in &syms[i..j] {
            sink.coefficient(level, band_index, sym);
        }
        i = j;
    }
}

/// Symbol frequencies for building the Huffman tables.
struct Frequencies {
    tag: Vec<u64>,
    run: Vec<u64>,
    position: Vec<u64>,
    value: Vec<u64>,
}

impl SyntaxSink for Frequencies {
    fn run(&mut self, substream: usize, length: u64) {
        self.tag[substream] += 1;
        self.run[unsigned_category(length - 1).0 as usize] += 1;
    }
    fn coefficient(&mut self, _level: usize, _band: usize, s: &Symbols) {
        for d in s.dpos {
            self.position[signed_category(d).0 as usize] += 1;
        }
        self.value[signed_category(s.step).0 as usize] += 1;
    }
}

/// Emits Huffman-coded syntax into a bit sink, counting bits per element.
struct HuffmanSink<'a, S: BitSink> {
    tables: &'a HuffmanTables,
    bits: S,
    breakdown: SizeBreakdown,
}

impl<S: BitSink> SyntaxSink for HuffmanSink<'_, S> {
    fn run(&mut self, substream: usize, length: u64) {
        let b0 = self.bits.bits();
        self.tables.tag.encode(substream, &mut self.bits);
        encode_unsigned(&self.tables.run, length - 1, &mut self.bits);
        self.breakdown.tag_bits += (self.bits.bits() - b0) as f64;
    }
    fn coefficient(&mut self, _level: usize, _band: usize, s: &Symbols) {
        let b0 = self.bits.bits();
        for d in s.dpos {
            encode_signed(&self.tables.position, d, &mut self.bits);
        }
        let b1 = self.bits.bits();
        self.bits.put_bit(s.negative);
        let b2 = self.bits.bits();
        encode_signed(&self.tables.value, s.step, &mut self.bits);
        let b3 = self.bits.bits();
        self.breakdown.position_bits += (b1 - b0) as f64;
        self.breakdown.sign_bits += (b2 - b1) as f64;
        self.breakdown.value_bits += (b3 - b2) as f64;
    }
}

/// Adaptive models of the range coder, fresh for every packet.
struct RangeModels {
    tag: AdaptiveUintModel,
    run: AdaptiveUintModel,
    position: Vec<[AdaptiveSintModel; 3]>,
    value: Vec<AdaptiveSintModel>,
}

impl RangeModels {
    fn new(header: &Header) -> RangeModels {
        RangeModels {
            tag: AdaptiveUintModel::new(),
            run: AdaptiveUintModel::new(),
            position: (0..=header.geometry.levels)
                .map(|_| std::array::from_fn(|_| AdaptiveSintModel::new()))
                .collect(),
            value: (0..header.geometry.band_count())
                .map(|_| AdaptiveSintModel::new())
                .collect(),
        }
    }
}

struct RangeSink {
    models: RangeModels,
    enc: RangeEncoder,
    breakdown: SizeBreakdown,
}

impl SyntaxSink for RangeSink {
    fn run(&mut self, substream: usize, length: u64) {
        let b0 = self.enc.bits_spent();
        self.models.tag.encode(&mut self.enc, substream as u64);
        self.models.run.encode(&mut self.enc, length - 1);
        self.breakdown.tag_bits += self.enc.bits_spent() - b0;
    }
    fn coefficient(&mut self, level: usize, band: usize, s: &Symbols) {
        let b0 = self.enc.bits_spent();
        for (a, d) in s.dpos.iter().enumerate() {
            self.models.position[level][a].encode(&mut self.enc, *d);
        }
        let b1 = self.enc.bits_spent();
        self.enc.encode_bypass(s.negative as u64, 1);
        let b2 = self.enc.bits_spent();
        self.models.value[band].encode(&mut self.enc, s.step);
        let b3 = self.enc.bits_spent();
        self.breakdown.position_bits += b1 - b0;
        self.breakdown.sign_bits += b2 - b1;
        self.breakdown.value_bits += b3 - b2;
    }
}

/// Builds the Huffman tables for a set of packets (two-pass coding: the tables are fitted to the
/// symbols actually sent, as the paper does).
fn fit_tables(header: &Header, symbolized: &[Vec<Symbols>]) -> HuffmanTables {
    let mut f = Frequencies {
        tag: vec![0; header.substream_count()],
        run: vec![0; CATEGORY_ALPHABET],
        position: vec![0; CATEGORY_ALPHABET],
        value: vec![0; CATEGORY_ALPHABET],
    };
    for syms in symbolized {
        emit(header, syms, &mut f);
    }
    HuffmanTables {
        tag: HuffmanCode::from_frequencies(&f.tag, 15),
        run: HuffmanCode::from_frequencies(&f.run, 15),
        position: HuffmanCode::from_frequencies(&f.position, 15),
        value: HuffmanCode::from_frequencies(&f.value, 15),
    }
}

/// Quantizes and codes packets in the paper's syntax (`header.coder` is Huffman or range);
/// returns their payloads and reconstructions in input order and where the bits went. For the
/// Huffman coder the tables are fitted to these packets and stored into `header.tables`.
pub(super) fn encode_packets(
    header: &mut Header,
    inputs: &[PacketInput],
) -> (Vec<Vec<u8>>, Vec<Vec<Coefficient>>, SizeBreakdown) {
    let (symbolized, reconstruction): (Vec<_>, Vec<_>) =
        inputs.iter().map(|p| symbolize(header, p)).unzip();
    let mut breakdown = SizeBreakdown::default();
    let mut payloads = Vec::with_capacity(inputs.len());
    if header.coder == CoderKind::Huffman {
        let tables = fit_tables(header, &symbolized);
        header.tables = Some(tables.clone());
        for syms in &symbolized {
            let mut sink = HuffmanSink {
                tables: &tables,
                bits: BitWriter::new(),
                breakdown,
            };
            emit(header, syms, &mut sink);
            breakdown = sink.breakdown;
            payloads.push(sink.bits.finish());
        }
    } else {
        header.tables = None;
        for syms in &symbolized {
            let mut sink = RangeSink {
                models: RangeModels::new(header),
                enc: RangeEncoder::new(),
                breakdown,
            };
            emit(header, syms, &mut sink);
            breakdown = sink.breakdown;
            payloads.push(sink.enc.finish());
        }
    }
    (payloads, reconstruction, breakdown)
}

/// Reads the syntax of one packet.
trait SyntaxSource {
    /// Bits consumed so far (exact for Huffman, byte-granular for the range coder).
    fn bits_read(&self) -> f64;
    fn run(&mut self) -> Result<(usize, u64), FormatError>;
    fn dpos(&mut self, level: usize, axis: usize) -> Result<i64, FormatError>;
    fn sign(&mut self) -> Result<bool, FormatError>;
    fn step(&mut self, band: usize) -> Result<i64, FormatError>;
}

struct HuffmanSource<'a> {
    reader: BitReader<'a>,
    tag: HuffmanDecoder,
    run: HuffmanDecoder,
    position: HuffmanDecoder,
    value: HuffmanDecoder,
}

impl SyntaxSource for HuffmanSource<'_> {
    fn bits_read(&self) -> f64 {
        self.reader.position() as f64
    }
    fn run(&mut self) -> Result<(usize, u64), FormatError> {
        let tag = self.tag.decode(&mut self.reader)?;
        let len = decode_unsigned(&self.run, &mut self.reader)?;
        Ok((tag, len.saturating_add(1)))
    }
    fn dpos(&mut self, _level: usize, _axis: usize) -> Result<i64, FormatError> {
        Ok(decode_signed(&self.position, &mut self.reader)?)
    }
    fn sign(&mut self) -> Result<bool, FormatError> {
        Ok(self.reader.get_bit()?)
    }
    fn step(&mut self, _band: usize) -> Result<i64, FormatError> {
        Ok(decode_signed(&self.value, &mut self.reader)?)
    }
}

struct RangeSource<'a> {
    dec: RangeDecoder<'a>,
    models: RangeModels,
}

impl SyntaxSource for RangeSource<'_> {
    fn bits_read(&self) -> f64 {
        8.0 * self.dec.bytes_read() as f64
    }
    fn run(&mut self) -> Result<(usize, u64), FormatError> {
        let tag = self.models.tag.decode(&mut self.dec)?;
        let len = self.models.run.decode(&mut self.dec)?;
        let tag = usize::try_from(tag).map_err(|_| invalid("packet", "run tag too large"))?;
        Ok((tag, len.saturating_add(1)))
    }
    fn dpos(&mut self, level: usize, axis: usize) -> Result<i64, FormatError> {
        Ok(self.models.position[level][axis].decode(&mut self.dec)?)
    }
    fn sign(&mut self) -> Result<bool, FormatError> {
        Ok(self.dec.decode_bypass(1) != 0)
    }
    fn step(&mut self, band: usize) -> Result<i64, FormatError> {
        Ok(self.models.value[band].decode(&mut self.dec)?)
    }
}

/// Decodes one packet's payload in the paper's syntax (`header.coder` is Huffman or range; a
/// [`super::packet::PayloadDecoder`]).
pub(super) fn decode(
    header: &Header,
    packet: &PacketFraming<'_>,
    breakdown: &mut SizeBreakdown,
) -> Result<Vec<Coefficient>, FormatError> {
    let (tile, layer, count, payload) = (packet.tile, packet.layer, packet.count, packet.payload);
    if header.coder == CoderKind::Huffman {
        let t = header
            .tables
            .as_ref()
            .ok_or_else(|| invalid("header", "Huffman coder without tables"))?;
        let mut src = HuffmanSource {
            reader: BitReader::new(payload),
            tag: HuffmanDecoder::new(&t.tag),
            run: HuffmanDecoder::new(&t.run),
            position: HuffmanDecoder::new(&t.position),
            value: HuffmanDecoder::new(&t.value),
        };
        decode_syntax(header, tile, layer, count, &mut src, breakdown)
    } else {
        let mut src = RangeSource {
            dec: RangeDecoder::new(payload),
            models: RangeModels::new(header),
        };
        decode_syntax(header, tile, layer, count, &mut src, breakdown)
    }
}

fn decode_syntax(
    header: &Header,
    tile: usize,
    layer: usize,
    count: usize,
    src: &mut impl SyntaxSource,
    bd: &mut SizeBreakdown,
) -> Result<Vec<Coefficient>, FormatError> {
    const W: &str = "packet";
    let nsub = header.substream_count();
    let nb = header.geometry.band_count();
    let bands = header.geometry.bands();
    let origin = header.tile_origin(tile);
    let mut chains: Vec<Option<Chain>> = vec![None; nsub];
    let mut prev_voxel = [0i64; 3];
    // The count is bounded but may still be large for a hostile packet: grow as decoded.
    let mut out = Vec::with_capacity(count.min(INITIAL_CAPACITY));
    while out.len() < count {
        let b0 = src.bits_read();
        let (sub, len) = src.run()?;
        bd.tag_bits += src.bits_read() - b0;
        if sub >= nsub {
            return Err(invalid(W, format!("substream {sub} of {nsub}")));
        }
        let Some(params) = header.substreams[sub] else {
            return Err(invalid(W, format!("substream {sub} has no parameters")));
        };
        if len > (count - out.len()) as u64 {
            return Err(invalid(
                W,
                format!("run of {len} exceeds the coefficient count"),
            ));
        }
        let (channel, band_index) = (sub / nb, sub % nb);
        let band = bands[band_index];
        let level = band.level as usize;
        let band_dims = header.geometry.band_dims(band);
        let chain = chains[sub]
            .get_or_insert_with(|| Chain::new(header.chain_start(sub, layer), params.delta as f64));
        for _ in 0..len {
            let b0 = src.bits_read();
            let mut pos = [0u32; 3];
            for a in 0..3 {
                let d = src.dpos(level, a)?;
                let local = (prev_voxel[a] >> level)
                    .checked_add(d)
                    .ok_or_else(|| invalid(W, "position delta overflows"))?;
                let lo = (origin[a] >> level) as i64;
                let hi = ((origin[a] + header.tile) >> level).min(band_dims[a]) as i64;
                if local < 0 || lo + local >= hi {
                    return Err(invalid(
                        W,
                        format!(
                            "position {local} on axis {a} outside tile band of {}",
                            hi - lo
                        ),
                    ));
                }
                pos[a] = (lo + local) as u32;
                prev_voxel[a] = local << level;
            }
            let b1 = src.bits_read();
            let negative = src.sign()?;
            let b2 = src.bits_read();
            let step = src.step(band_index)?;
            let b3 = src.bits_read();
            bd.position_bits += b1 - b0;
            bd.sign_bits += b2 - b1;
            bd.value_bits += b3 - b2;
            let mag = chain.decode(step)?;
            let v = if negative { -mag } else { mag } as f32;
            if !v.is_finite() {
                return Err(invalid(W, "decoded value is not finite"));
            }
            out.push(Coefficient {
                channel: channel as u8,
                band,
                pos,
                value: v,
            });
        }
    }
    Ok(out)
}
