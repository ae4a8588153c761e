//! Tabulated optical constants n(λ), k(λ) of pillar materials from the literature, selectable
//! by name.
//!
//! Each table is a CSV file under `metalib/data/materials/` compiled into the crate: `#` header
//! lines give the name, the kind of film, the full citation and how the values were obtained;
//! then `wavelength_nm,n,k` rows in increasing wavelength. Between rows, n and k are each
//! interpolated **linearly in wavelength** (so every tabulated row is reproduced exactly, and
//! between two rows the value lies between theirs); outside the tabulated range the lookup is
//! an error, never an extrapolation.

use crate::error::MetalibError;
use crate::material::Materials;
use std::sync::OnceLock;

/// One material table: citation metadata and rows (λ in nm, n, k).
#[derive(Debug, Clone, PartialEq)]
pub struct DispersionTable {
    /// Name used by `--material` (lower case, no spaces).
    pub name: String,
    /// What was measured (film kind, thickness, temperature).
    pub kind: String,
    /// Full citation of the published data.
    pub citation: String,
    /// How the values were obtained (tabulated, digitised, model evaluated) and transcribed.
    pub values: String,
    /// Remarks on the data (gaps, zero k, unknown deposition method).
    pub notes: Vec<String>,
    /// Rows (wavelength in nm, n, k), wavelength strictly increasing.
    pub rows: Vec<(f64, f64, f64)>,
}

/// The embedded tables, as (file name, text).
const SOURCES: [(&str, &str); 6] = [
    (
        "pierce-spicer-1972.csv",
        include_str!("../data/materials/pierce-spicer-1972.csv"),
    ),
    (
        "franta-2013-asih.csv",
        include_str!("../data/materials/franta-2013-asih.csv"),
    ),
    (
        "karaman-2025-asi.csv",
        include_str!("../data/materials/karaman-2025-asi.csv"),
    ),
    (
        "green-2008-csi.csv",
        include_str!("../data/materials/green-2008-csi.csv"),
    ),
    (
        "sputtered-2020-asi.csv",
        include_str!("../data/materials/sputtered-2020-asi.csv"),
    ),
    (
        "sputtered-2020-asih.csv",
        include_str!("../data/materials/sputtered-2020-asih.csv"),
    ),
];

impl DispersionTable {
    /// Parses the CSV format described in the module documentation.
    pub fn parse(file: &str, text: &str) -> Result<Self, MetalibError> {
        let bad = |why: String| MetalibError::Format {
            path: file.to_string(),
            reason: why,
        };
        let (mut name, mut kind, mut citation, mut values) = (
            None::<String>,
            None::<String>,
            None::<String>,
            None::<String>,
        );
        let mut notes = Vec::new();
        let mut rows: Vec<(f64, f64, f64)> = Vec::new();
        let mut header_seen = false;
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            if let Some(meta) = line.strip_prefix('#') {
                let (key, val) = meta
                    .split_once(':')
                    .ok_or_else(|| bad(format!("line {}: `# key: value` expected", i + 1)))?;
                let val = val.trim().to_string();
                match key.trim() {
                    "name" => name = Some(val),
                    "kind" => kind = Some(val),
                    "citation" => citation = Some(val),
                    "values" => values = Some(val),
                    "note" => notes.push(val),
                    k => return Err(bad(format!("line {}: unknown key `{k}`", i + 1))),
                }
                continue;
            }
            if !header_seen {
                if line != "wavelength_nm,n,k" {
                    return Err(bad(format!(
                        "line {}: header `wavelength_nm,n,k` expected",
                        i + 1
                    )));
                }
                header_seen = true;
                continue;
            }
            let f: Vec<f64> = line
                .split(',')
                .map(|v| v.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|e| bad(format!("line {}: {e}", i + 1)))?;
            let [l, n, k] = f[..] else {
                return Err(bad(format!("line {}: three columns expected", i + 1)));
            };
            if !(l.is_finite() && l > 0.0 && n.is_finite() && n > 0.0 && k.is_finite() && k >= 0.0)
            {
                return Err(bad(format!(
                    "line {}: need λ > 0, n > 0, k ≥ 0, finite",
                    i + 1
                )));
            }
            if rows.last().is_some_and(|r| r.0 >= l) {
                return Err(bad(format!(
                    "line {}: wavelengths must increase strictly",
                    i + 1
                )));
            }
            rows.push((l, n, k));
        }
        if rows.len() < 2 {
            return Err(bad("fewer than two rows".into()));
        }
        let need = |v: Option<String>, k: &str| v.ok_or_else(|| bad(format!("missing `# {k}:`")));
        Ok(Self {
            name: need(name, "name")?,
            kind: need(kind, "kind")?,
            citation: need(citation, "citation")?,
            values: need(values, "values")?,
            notes,
            rows,
        })
    }

    /// Tabulated wavelength range (m).
    pub fn range_m(&self) -> (f64, f64) {
        let first = self.rows.first().map_or(f64::NAN, |r| r.0);
        let last = self.rows.last().map_or(f64::NAN, |r| r.0);
        (first * 1e-9, last * 1e-9)
    }

    /// (n, k) at `wavelength_m`, linear in wavelength between the two neighbouring rows;
    /// an error outside the tabulated range.
    pub fn nk_at(&self, wavelength_m: f64) -> Result<(f64, f64), MetalibError> {
        let l = wavelength_m * 1e9;
        let (first, last) = match (self.rows.first(), self.rows.last()) {
            (Some(a), Some(b)) if self.rows.len() >= 2 => (a.0, b.0),
            _ => {
                return Err(MetalibError::InvalidData(format!(
                    "`{}` has fewer than two rows",
                    self.name
                )));
            }
        };
        if !l.is_finite() {
            return Err(MetalibError::param(
                "wavelength",
                format!("must be finite, got {wavelength_m} m"),
            ));
        }
        // Metres → nm is not exact in binary: a wavelength within 1e-9 relative of a row
        // (e.g. 1378 nm given as 1378e-9 m) is that row.
        let tol = 1e-9 * l.abs();
        if let Some(r) = self.rows.iter().find(|r| (r.0 - l).abs() <= tol) {
            return Ok((r.1, r.2));
        }
        if !(l >= first && l <= last) {
            let (lo, hi) = self.range_m();
            return Err(MetalibError::param(
                "wavelength",
                format!(
                    "{} nm lies outside the {:.1}–{:.1} nm tabulated for material `{}`",
                    l,
                    lo * 1e9,
                    hi * 1e9,
                    self.name
                ),
            ));
        }
        // first < λ < last and λ is no row, so 1 ≤ j < len.
        let j = self
            .rows
            .partition_point(|r| r.0 < l)
            .clamp(1, self.rows.len() - 1);
        let (a, b) = (self.rows[j - 1], self.rows[j]);
        let w = (l - a.0) / (b.0 - a.0);
        Ok((a.1 + w * (b.1 - a.1), a.2 + w * (b.2 - a.2)))
    }

    /// Default cell materials with this table's pillar (n, k) at `wavelength_m`.
    pub fn materials_at(&self, wavelength_m: f64) -> Result<Materials, MetalibError> {
        let (n, k) = self.nk_at(wavelength_m)?;
        Ok(Materials {
            n_pillar: n,
            k_pillar: k,
            ..Materials::default()
        })
    }
}

/// Every embedded table, parsed once (an embedded file that does not parse is reported as an
/// error by every lookup, and fails the crate's tests).
pub fn tables() -> Result<&'static [DispersionTable], MetalibError> {
    static T: OnceLock<Result<Vec<DispersionTable>, String>> = OnceLock::new();
    T.get_or_init(|| {
        SOURCES
            .iter()
            .map(|(f, t)| DispersionTable::parse(f, t).map_err(|e| e.to_string()))
            .collect()
    })
    .as_ref()
    .map(|v| v.as_slice())
    .map_err(|e| MetalibError::InvalidData(e.clone()))
}

/// Names of the embedded tables, in table order.
pub fn names() -> Vec<String> {
    tables()
        .map(|t| t.iter().map(|m| m.name.clone()).collect())
        .unwrap_or_default()
}

/// The table called `name`; the error lists every known name.
pub fn by_name(name: &str) -> Result<&'static DispersionTable, MetalibError> {
    let t = tables()?;
    t.iter().find(|m| m.name == name).ok_or_else(|| {
        MetalibError::param(
            "material",
            format!(
                "unknown material `{name}`; known: {}",
                t.iter()
                    .map(|m| m.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_embedded_table_parses_with_a_citation_and_covers_800_to_1100_nm() {
        let t = tables().unwrap();
        assert_eq!(t.len(), SOURCES.len());
        for m in t {
            assert!(
                m.citation.contains("(19") || m.citation.contains("(20"),
                "{}",
                m.name
            );
            let (lo, hi) = m.range_m();
            assert!(lo <= 800e-9 && hi >= 1100e-9, "{}: {lo:e}–{hi:e}", m.name);
        }
        let mut n = names();
        n.sort();
        n.dedup();
        assert_eq!(n.len(), t.len(), "names are unique");
    }

    #[test]
    fn interpolation_reproduces_every_row_exactly() {
        for m in tables().unwrap() {
            for &(l, n, k) in &m.rows {
                assert_eq!(m.nk_at(l * 1e-9).unwrap(), (n, k), "{} at {l} nm", m.name);
            }
        }
    }

    #[test]
    fn interpolation_is_continuous_and_stays_between_neighbouring_rows() {
        for m in tables().unwrap() {
            for w in m.rows.windows(2) {
                let (a, b) = (w[0], w[1]);
                let mut prev = (a.1, a.2);
                for i in 1..=64 {
                    let l = a.0 + (b.0 - a.0) * i as f64 / 64.0;
                    let (n, k) = m.nk_at(l * 1e-9).unwrap();
                    let inside =
                        |v: f64, p: f64, q: f64| v >= p.min(q) - 1e-12 && v <= p.max(q) + 1e-12;
                    assert!(
                        inside(n, a.1, b.1) && inside(k, a.2, b.2),
                        "{} at {l}",
                        m.name
                    );
                    // Monotone along the interval, in the direction of the end rows.
                    assert!((n - prev.0) * (b.1 - a.1) >= -1e-15, "{} n at {l}", m.name);
                    assert!((k - prev.1) * (b.2 - a.2) >= -1e-15, "{} k at {l}", m.name);
                    // Continuity: a step of 1/64 of the interval moves at most 1/64 of the jump.
                    assert!((n - prev.0).abs() <= (b.1 - a.1).abs() / 64.0 + 1e-12);
                    assert!((k - prev.1).abs() <= (b.2 - a.2).abs() / 64.0 + 1e-12);
                    prev = (n, k);
                }
            }
        }
    }

    #[test]
    fn named_materials_at_940_nm_give_the_tables_values() {
        // Green 2008 and Karaman 2025 tabulate 940 nm itself.
        assert_eq!(
            by_name("green-2008-csi").unwrap().nk_at(940e-9).unwrap(),
            (3.595, 1.3689e-3)
        );
        assert_eq!(
            by_name("karaman-2025-asi").unwrap().nk_at(940e-9).unwrap(),
            (3.979189, 0.0)
        );
        // Pierce & Spicer between 885.6 nm (3.77, 0.0401) and 953.8 nm (3.68, 0): the
        // crate's default constants (3.70, 0.008) are this value to two significant digits.
        let (n, k) = by_name("pierce-spicer-1972")
            .unwrap()
            .nk_at(940e-9)
            .unwrap();
        let w = (940.0 - 885.6) / (953.8 - 885.6);
        assert!((n - (3.77 - 0.09 * w)).abs() < 1e-12 && (k - 0.0401 * (1.0 - w)).abs() < 1e-12);
        assert!((n - crate::material::A_SI_N_940).abs() < 0.005);
        assert!((k - crate::material::A_SI_K_940).abs() < 0.0005);
        // Franta 2013 between 933.254 nm and 954.993 nm.
        let (n, k) = by_name("franta-2013-asih").unwrap().nk_at(940e-9).unwrap();
        assert!(n < 3.787655 && n > 3.774782 && k < 1.904373e-3 && k > 1.663291e-3);
    }

    /// The two sputtered-film tables are the Cody–Lorentz model of their parameters
    /// (`cody_lorentz::SPUTTERED_2020`) evaluated at every row, to the digits printed.
    #[test]
    fn sputtered_tables_are_their_cody_lorentz_model() {
        for (name, model, _) in crate::cody_lorentz::SPUTTERED_2020 {
            let t = by_name(name).unwrap();
            assert_eq!(t.rows.len(), 51, "{name}: 700-1200 nm every 10 nm");
            for &(l, n, k) in &t.rows {
                let (mn, mk) = model.nk_at(l * 1e-9).unwrap();
                assert!((n - mn).abs() <= 5e-7, "{name} at {l} nm: n {n} vs {mn}");
                assert!(
                    (k - mk).abs() <= 5e-7 * mk.max(1e-300),
                    "{name} at {l} nm: k {k} vs {mk}"
                );
            }
        }
        // 940 nm is a row: above the unhydrogenated film's gap (lossy), below the
        // hydrogenated film's (k = 0, no Urbach tail in the source).
        let (n, k) = by_name("sputtered-2020-asi")
            .unwrap()
            .nk_at(940e-9)
            .unwrap();
        assert!(
            (n - 4.157).abs() < 1e-3 && (k - 0.0446).abs() < 1e-4,
            "{n} {k}"
        );
        let (n, k) = by_name("sputtered-2020-asih")
            .unwrap()
            .nk_at(940e-9)
            .unwrap();
        assert!((n - 3.639).abs() < 1e-3 && k == 0.0, "{n} {k}");
    }

    #[test]
    fn unknown_names_and_out_of_range_wavelengths_are_errors() {
        let e = by_name("unobtainium").unwrap_err().to_string();
        for n in names() {
            assert!(e.contains(&n), "{e}");
        }
        let m = by_name("green-2008-csi").unwrap();
        for l in [
            500e-9,
            1500e-9,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            0.0,
        ] {
            assert!(m.nk_at(l).is_err(), "{l}");
        }
        // A hand-built table with too few rows is an error, not a panic.
        for rows in [vec![], vec![(940.0, 3.6, 0.0)]] {
            let t = DispersionTable { rows, ..m.clone() };
            assert!(t.nk_at(940e-9).is_err());
        }
    }

    #[test]
    fn malformed_tables_are_refused() {
        let head = "# name: x\n# kind: y\n# citation: z (2000)\n# values: v\nwavelength_nm,n,k\n";
        assert!(DispersionTable::parse("ok", &format!("{head}1,2,0\n2,3,0\n")).is_ok());
        for body in [
            "1,2,0\n",
            "2,2,0\n1,3,0\n",
            "1,2,0\n1,3,0\n",
            "1,2,-1\n2,3,0\n",
            "1,nan,0\n2,3,0\n",
            "1,2\n2,3,0\n",
        ] {
            assert!(
                DispersionTable::parse("bad", &format!("{head}{body}")).is_err(),
                "{body}"
            );
        }
        assert!(DispersionTable::parse("bad", "wavelength_nm,n,k\n1,2,0\n2,3,0\n").is_err());
    }
}
