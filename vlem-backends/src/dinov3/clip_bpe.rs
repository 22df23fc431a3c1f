//! OpenAI CLIP's byte-level BPE tokenizer, read from `bpe_simple_vocab_16e6.txt.gz`: the
//! tokenizer of the dino.txt text tower.
//!
//! Why it exists: dino.txt ships no `tokenizer.json`; Meta's code tokenises with OpenAI's
//! `SimpleTokenizer` over the gzipped merge list, and the ids must be exactly those the text
//! tower was trained on. This module owns building the vocabulary from that file and encoding
//! text the same way (checked against Meta's tokenizer on 20 texts,
//! `vlem-backends/goldens/clip_bpe/`):
//!
//! 1. cleaning: the parts of `ftfy.fix_text` that change typed text (control characters removed,
//!    curly quotes straightened, Latin ligatures and full-width forms expanded, NFC), HTML
//!    entities unescaped as Python's `html.unescape` does for the common ones, surrounding
//!    whitespace stripped, runs of whitespace collapsed to one space, lower case;
//! 2. pre-tokenising with CLIP's pattern: the special-token strings, the contractions `'s 't 're
//!    've 'm 'll 'd`, runs of letters, single digits, runs of other non-space characters;
//! 3. each piece as UTF-8 bytes mapped to CLIP's printable stand-in characters, its last symbol
//!    marked with `</w>`, and merged pair by pair in the rank order of the file;
//! 4. `[start] + ids + [end]`, cut to the context length with the last id set to `end`.
//!
//! Not reproduced: ftfy's repair of mis-decoded text (mojibake such as `cafÃ©`), which needs its
//! own tables; such text is tokenised as it is.

use std::collections::HashMap;
use std::io::Read;
use std::path::Path;

use regex::Regex;

use crate::error::BackendError;

/// The file's name as Meta and OpenAI ship it.
pub const VOCAB_FILE: &str = "bpe_simple_vocab_16e6.txt.gz";

/// Merges the released vocabulary uses: the file holds more, OpenAI's tokenizer reads the first
/// `49152 - 256 - 2` (a vocabulary of 49408 with the 512 byte symbols and 2 special tokens).
const MERGES_USED: usize = 49152 - 256 - 2;

const START: &str = "<|startoftext|>";
const END: &str = "<|endoftext|>";

/// CLIP's pre-tokenising pattern (case-insensitive, as OpenAI compiles it).
const PATTERN: &str =
    r"(?i)<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|\p{L}+|\p{N}|[^\s\p{L}\p{N}]+";

/// CLIP's BPE tokenizer. Thread-safe, immutable once loaded.
#[derive(Clone, Debug)]
pub struct ClipBpe {
    ids: HashMap<String, u32>,
    ranks: HashMap<(String, String), u32>,
    byte_symbols: Vec<char>,
    pattern: Regex,
    start: u32,
    end: u32,
}

/// The bytes 0..=255 as CLIP's printable stand-ins: printable Latin-1 bytes stand for
/// themselves, the others (controls, space, soft hyphen) for the code points from 256 on, in
/// byte order. Also the order of the first 256 vocabulary entries (printable ones first).
fn byte_symbols() -> (Vec<char>, Vec<u8>) {
    let printable = |b: u32| (0x21..=0x7e).contains(&b) || (0xa1..=0xac).contains(&b) || b >= 0xae;
    let mut symbols = vec!['\0'; 256];
    let mut order: Vec<u8> = (0u8..=255).filter(|&b| printable(u32::from(b))).collect();
    let mut next = 256u32;
    for b in 0u8..=255 {
        let code = u32::from(b);
        symbols[usize::from(b)] = if printable(code) {
            char::from(b)
        } else {
            order.push(b);
            let c = char::from_u32(next).unwrap_or('\u{fffd}');
            next += 1;
            c
        };
    }
    (symbols, order)
}

impl ClipBpe {
    /// Reads the gzipped merge list (`bpe_simple_vocab_16e6.txt.gz`).
    ///
    /// # Errors
    /// [`BackendError::InvalidModelFile`] for a file that cannot be read or decompressed, or
    /// whose lines are not merges.
    pub fn load(path: &Path) -> Result<Self, BackendError> {
        let invalid = |reason: String| BackendError::InvalidModelFile {
            path: path.to_path_buf(),
            reason,
        };
        let file =
            std::fs::File::open(path).map_err(|e| invalid(format!("cannot open it: {e}")))?;
        let mut text = String::new();
        flate2::read::GzDecoder::new(file)
            .read_to_string(&mut text)
            .map_err(|e| invalid(format!("not a gzipped UTF-8 text file: {e}")))?;
        Self::parse(&text).map_err(invalid)
    }

    /// From the merge list's text: a header line, then one `left right` pair per line.
    ///
    /// # Errors
    /// [`BackendError::InvalidInput`] naming a line that is not a pair, or a text without merges.
    pub fn from_merges(text: &str) -> Result<Self, BackendError> {
        Self::parse(text)
            .map_err(|reason| BackendError::InvalidInput(format!("CLIP merge list: {reason}")))
    }

    /// [`Self::from_merges`], the error in words for the caller to place (a file, a text).
    fn parse(text: &str) -> Result<Self, String> {
        let mut merges = Vec::new();
        for (index, line) in text.lines().enumerate().skip(1).take(MERGES_USED) {
            if line.is_empty() {
                continue;
            }
            let mut parts = line.split(' ');
            match (parts.next(), parts.next(), parts.next()) {
                (Some(a), Some(b), None) if !a.is_empty() && !b.is_empty() => {
                    merges.push((a.to_owned(), b.to_owned()));
                }
                _ => return Err(format!("line {} is not a merge pair: {line:?}", index + 1)),
            }
        }
        if merges.is_empty() {
            return Err("it holds no merges".to_owned());
        }
        let (symbols, order) = byte_symbols();
        let mut vocab: Vec<String> = order
            .iter()
            .map(|&b| symbols[usize::from(b)].to_string())
            .collect();
        let words: Vec<String> = vocab.iter().map(|s| format!("{s}</w>")).collect();
        vocab.extend(words);
        vocab.extend(merges.iter().map(|(a, b)| format!("{a}{b}")));
        vocab.push(START.to_owned());
        vocab.push(END.to_owned());
        let count = u32::try_from(vocab.len()).map_err(|_| "too many merges".to_owned())?;
        // Later duplicates win, as in a Python dict built from the same list.
        let ids: HashMap<String, u32> = vocab.into_iter().zip(0..count).collect();
        let ranks = merges.into_iter().zip(0..count).collect();
        let pattern = Regex::new(PATTERN).map_err(|e| format!("tokenizer pattern: {e}"))?;
        Ok(Self {
            ids,
            ranks,
            byte_symbols: symbols,
            pattern,
            start: count - 2,
            end: count - 1,
        })
    }

    /// The start-of-text id (49406 for the released vocabulary).
    pub fn start_id(&self) -> u32 {
        self.start
    }

    /// The end-of-text id (49407 for the released vocabulary), the largest id.
    pub fn end_id(&self) -> u32 {
        self.end
    }

    /// Entries in the vocabulary (49408 for the released one).
    pub fn vocab_size(&self) -> usize {
        self.end as usize + 1
    }

    /// `[start] + encode(text) + [end]`, cut to `context` ids with the last set to end-of-text,
    /// not padded (the causal text tower reads up to the end-of-text id only).
    pub fn tokenize(&self, text: &str, context: usize) -> Vec<u32> {
        let mut ids = Vec::with_capacity(16);
        ids.push(self.start);
        ids.extend(self.encode(text));
        ids.push(self.end);
        if ids.len() > context {
            ids.truncate(context);
            if let Some(last) = ids.last_mut() {
                *last = self.end;
            }
        }
        ids
    }

    /// The BPE ids of `text`, without start and end.
    pub fn encode(&self, text: &str) -> Vec<u32> {
        let text = clean(text);
        let mut ids = Vec::new();
        for piece in self.pattern.find_iter(&text) {
            let piece = piece.as_str();
            match piece {
                START => ids.push(self.start),
                END => ids.push(self.end),
                _ => {
                    let symbols: Vec<String> = piece
                        .bytes()
                        .map(|b| self.byte_symbols[usize::from(b)].to_string())
                        .collect();
                    // Every symbol merge produces is in the vocabulary by construction.
                    ids.extend(self.bpe(symbols).iter().filter_map(|s| self.ids.get(s)));
                }
            }
        }
        ids
    }

    /// Merges `symbols` (one piece; its last symbol gets the `</w>` mark) by rank.
    fn bpe(&self, mut word: Vec<String>) -> Vec<String> {
        if let Some(last) = word.last_mut() {
            last.push_str("</w>");
        }
        loop {
            let best = word
                .windows(2)
                .filter_map(|pair| {
                    self.ranks
                        .get(&(pair[0].clone(), pair[1].clone()))
                        .map(|&rank| (rank, pair))
                })
                .min_by_key(|(rank, _)| *rank);
            let Some((_, pair)) = best else {
                return word;
            };
            let (first, second) = (pair[0].clone(), pair[1].clone());
            let mut merged = Vec::with_capacity(word.len());
            let mut i = 0;
            while i < word.len() {
                if i + 1 < word.len() && word[i] == first && word[i + 1] == second {
                    merged.push(format!("{first}{second}"));
                    i += 2;
                } else {
                    merged.push(std::mem::take(&mut word[i]));
                    i += 1;
                }
            }
            word = merged;
            if word.len() == 1 {
                return word;
            }
        }
    }
}

/// The cleaning of OpenAI's tokenizer (`ftfy.fix_text`, `html.unescape` twice, strip, whitespace
/// collapsed, lower case), as far as the module documentation says.
fn clean(text: &str) -> String {
    // ftfy unescapes HTML itself when the text has no tags ("auto"), then the tokenizer twice.
    let rounds = if text.contains('<') { 2 } else { 3 };
    let mut text = fix_text(text);
    for _ in 0..rounds {
        text = unescape_html(&text);
    }
    let collapsed = text.split_whitespace().collect::<Vec<_>>().join(" ");
    collapsed.to_lowercase()
}

/// The parts of ftfy's default `fix_text` that apply to text that was decoded correctly.
fn fix_text(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            // Control characters other than whitespace are removed.
            '\u{0}'..='\u{8}' | '\u{b}' | '\u{e}'..='\u{1f}' | '\u{7f}' => {}
            '\u{2018}' | '\u{2019}' | '\u{201a}' | '\u{201b}' => out.push('\''),
            '\u{201c}' | '\u{201d}' | '\u{201e}' | '\u{201f}' => out.push('"'),
            '\u{fb00}' => out.push_str("ff"),
            '\u{fb01}' => out.push_str("fi"),
            '\u{fb02}' => out.push_str("fl"),
            '\u{fb03}' => out.push_str("ffi"),
            '\u{fb04}' => out.push_str("ffl"),
            '\u{fb05}' | '\u{fb06}' => out.push_str("st"),
            '\u{3000}' => out.push(' '),
            // Full-width ASCII forms become ASCII.
            '\u{ff01}'..='\u{ff5e}' => {
                out.push(char::from_u32(u32::from(c) - 0xfee0).unwrap_or(c));
            }
            _ => out.push(c),
        }
    }
    let mut normalised = tokenizers::NormalizedString::from(out.as_str());
    normalised.nfc();
    normalised.get().to_owned()
}

/// Decodes numeric character references and the common named entities (`&amp; &lt; &gt; &quot;
/// &apos; &nbsp;`) once; anything else is kept as it is.
fn unescape_html(text: &str) -> String {
    if !text.contains('&') {
        return text.to_owned();
    }
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(at) = rest.find('&') {
        out.push_str(&rest[..at]);
        let tail = &rest[at..];
        match decode_entity(tail) {
            Some((decoded, used)) => {
                out.push(decoded);
                rest = &tail[used..];
            }
            None => {
                out.push('&');
                rest = &tail[1..];
            }
        }
    }
    out.push_str(rest);
    out
}

/// The character an entity at the start of `s` (which starts with `&`) stands for, and the
/// bytes it takes.
fn decode_entity(s: &str) -> Option<(char, usize)> {
    let body = s.get(1..)?;
    if let Some(number) = body.strip_prefix('#') {
        let (digits, radix, skip) = match number.strip_prefix(['x', 'X']) {
            Some(hex) => (hex, 16, 3),
            None => (number, 10, 2),
        };
        let len = digits
            .find(|c: char| !c.is_digit(radix))
            .unwrap_or(digits.len());
        let code = u32::from_str_radix(digits.get(..len)?, radix).ok()?;
        let semicolon = usize::from(digits[len..].starts_with(';'));
        // As Python: NUL and out-of-range references become U+FFFD.
        let c = match code {
            0 => '\u{fffd}',
            _ => char::from_u32(code).unwrap_or('\u{fffd}'),
        };
        return Some((c, skip + len + semicolon));
    }
    const NAMED: [(&str, char); 6] = [
        ("amp", '&'),
        ("lt", '<'),
        ("gt", '>'),
        ("quot", '"'),
        ("apos", '\''),
        ("nbsp", '\u{a0}'),
    ];
    NAMED.iter().find_map(|(name, c)| {
        let after = body.strip_prefix(name)?;
        if after.starts_with(';') {
            Some((*c, 1 + name.len() + 1))
        } else if *name != "apos" {
            // HTML's legacy entities decode without the semicolon too (`&amp` -> `&`).
            Some((*c, 1 + name.len()))
        } else {
            None
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A vocabulary of four merges: `c a`, `ca t</w>`, `h a`, `ha t</w>`.
    fn tiny() -> ClipBpe {
        ClipBpe::from_merges("#version: test\nc a\nca t</w>\nh a\nha t</w>\n").unwrap()
    }

    #[test]
    fn ids_follow_the_vocabulary_layout() {
        let bpe = tiny();
        // 256 byte symbols, 256 word-end forms, 4 merges, start, end.
        assert_eq!(bpe.vocab_size(), 256 + 256 + 4 + 2);
        assert_eq!((bpe.start_id(), bpe.end_id()), (516, 517));
        // 'a' is the 65th printable byte (after '!'..'`'), so id 64; its word-end form 256 later.
        assert_eq!(bpe.encode("a"), vec![64 + 256]);
        // "cat" merges fully: merge 1 (`ca t</w>`) has id 512 + 1.
        assert_eq!(bpe.encode("cat"), vec![513]);
        assert_eq!(bpe.encode("HAT hat"), vec![515, 515]);
        // No merge for "at" alone: two symbols, the last marked as a word end.
        assert_eq!(bpe.encode("at"), vec![64, 83 + 256]);
    }

    #[test]
    fn byte_symbols_are_printable_and_distinct() {
        let (symbols, order) = byte_symbols();
        assert_eq!(symbols[usize::from(b'!')], '!');
        assert_eq!(symbols[0], '\u{100}');
        assert_eq!(symbols[usize::from(b' ')], '\u{120}');
        let mut sorted = order.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), 256);
    }

    #[test]
    fn tokenize_cuts_to_the_context_ending_with_end_of_text() {
        let bpe = tiny();
        let ids = bpe.tokenize("cat cat cat cat cat", 4);
        assert_eq!(ids, vec![516, 513, 513, 517]);
        assert_eq!(bpe.tokenize("", 77), vec![516, 517]);
    }

    #[test]
    fn html_entities_decode_like_python() {
        assert_eq!(
            unescape_html("a &amp; b &lt;c&gt; &#39;d&#x41;"),
            "a & b <c> 'dA"
        );
        assert_eq!(
            unescape_html("&amp &unknown; & alone"),
            "& &unknown; & alone"
        );
        assert_eq!(
            clean("  The\u{2019}s \u{fb01}ne\t\tＣＡＴ "),
            "the's fine cat"
        );
    }

    #[test]
    fn malformed_merge_lists_are_errors() {
        let empty = ClipBpe::from_merges("#version\n").unwrap_err().to_string();
        assert_eq!(empty, "CLIP merge list: it holds no merges");
        let triple = ClipBpe::from_merges("#version\na b c\n")
            .unwrap_err()
            .to_string();
        assert!(triple.contains("line 2 is not a merge pair"), "{triple}");
    }
}
