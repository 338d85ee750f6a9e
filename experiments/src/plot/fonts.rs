//! Finding a font at run time for plotters' `ab_glyph` text.
//!
//! Searched in order: the file named by `EBMPC_FONT`, DejaVu Sans and Liberation Sans where
//! Debian and Fedora install them, then the first `.ttf` under the usual font folders (sans
//! faces first). The font is registered once per process.

use plotters::style::FontStyle;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Well-known locations of a sans-serif TTF.
const KNOWN: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation-sans/LiberationSans-Regular.ttf",
    "/System/Library/Fonts/Supplemental/Arial.ttf",
];

/// Folders searched for any `.ttf` when none of [`KNOWN`] exists.
const FOLDERS: &[&str] = &["/usr/share/fonts", "/usr/local/share/fonts"];

/// Registers a font for [`super::FAMILY`] on first call; returns whether text can be drawn.
/// Logs a warning (once) when no font was found.
pub fn ensure() -> bool {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    *REGISTERED.get_or_init(|| match find().and_then(|p| register(&p).then_some(p)) {
        Some(path) => {
            tracing::debug!(font = %path.display(), "figure text font");
            true
        }
        None => {
            tracing::warn!(
                "no usable TTF font found (set EBMPC_FONT=/path/to/font.ttf): figures are drawn \
                 without text"
            );
            false
        }
    })
}

/// The font file to use, if any.
pub fn find() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("EBMPC_FONT").map(PathBuf::from)
        && path.is_file()
    {
        return Some(path);
    }
    if let Some(path) = KNOWN.iter().map(Path::new).find(|p| p.is_file()) {
        return Some(path.to_path_buf());
    }
    let mut found = Vec::new();
    for folder in FOLDERS {
        collect_ttf(Path::new(folder), 4, &mut found);
    }
    found.sort_by_key(|p| {
        let name = p.file_name().map(|n| n.to_string_lossy().to_lowercase());
        let name = name.unwrap_or_default();
        (
            !name.contains("sans"),
            name.contains("bold") || name.contains("italic"),
            p.clone(),
        )
    });
    found.into_iter().next()
}

fn collect_ttf(dir: &Path, depth: u32, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() && depth > 0 {
            collect_ttf(&path, depth - 1, out);
        } else if path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("ttf"))
        {
            out.push(path);
        }
    }
}

/// Reads and registers `path` as the figures' font; false if it cannot be read or parsed.
fn register(path: &Path) -> bool {
    let Ok(bytes) = std::fs::read(path) else {
        return false;
    };
    // plotters keeps the font for the life of the process and wants `'static` bytes.
    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
    plotters::style::register_font(super::FAMILY, FontStyle::Normal, bytes).is_ok()
}
