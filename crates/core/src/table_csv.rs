//! The CSV that measured tables share (the lens's calibration and the panel's transfer): `#`
//! lines are comments (the provenance the calibrating command writes), the first other line
//! names the columns, two named columns are read and any others are kept for people.

/// How one kind of table names its columns, for reading and for messages.
pub(crate) struct TableColumns<'a> {
    /// The two columns read, in order.
    pub names: [&'a str; 2],
    /// What a row is ("point", "level").
    pub row: &'a str,
    /// What the columns are, for a header that lacks one.
    pub meaning: &'a str,
    /// What a cell must be ("a number", "a number of diopters").
    pub number: &'a str,
}

impl TableColumns<'_> {
    /// The two columns of every row of `text` with the row's line in the file (from 1); a
    /// message saying what is wrong otherwise.
    pub fn read(&self, text: &str) -> Result<Vec<(usize, [f64; 2])>, String> {
        let mut rows = text
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l.trim()))
            .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
        let Some((_, header)) = rows.next() else {
            let [a, b] = self.names;
            return Err(format!(
                "no header line: expected columns {a},{b} (then one row per {})",
                self.row
            ));
        };
        let names: Vec<&str> = header.split(',').map(str::trim).collect();
        let column = |want: &str| {
            names.iter().position(|n| *n == want).ok_or_else(|| {
                format!(
                    "no {want} column in the header {header:?}: expected {}",
                    self.meaning
                )
            })
        };
        let at = [column(self.names[0])?, column(self.names[1])?];
        rows.map(|(line, row)| {
            let cells: Vec<&str> = row.split(',').map(str::trim).collect();
            let mut values = [0.0; 2];
            for (value, (&i, what)) in values.iter_mut().zip(at.iter().zip(self.names)) {
                let cell = cells.get(i).copied().unwrap_or("");
                *value = cell
                    .parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| {
                        format!("line {line}: {what} {cell:?} is not {}", self.number)
                    })?;
            }
            Ok((line, values))
        })
        .collect()
    }

    /// The table as CSV: `comments` as `#` lines, the header (the two columns, then
    /// `extra_names`), then one line per point (already formatted, `a,b`) followed by its row
    /// of `extra` values, if any.
    pub fn write(
        &self,
        comments: &[String],
        points: impl Iterator<Item = String>,
        extra_names: &[&str],
        extra: &[Vec<String>],
    ) -> String {
        let mut out = String::new();
        for c in comments {
            for l in c.lines() {
                out += &format!("# {l}\n");
            }
        }
        out += &self.names.join(",");
        for n in extra_names {
            out += &format!(",{n}");
        }
        out.push('\n');
        for (k, point) in points.enumerate() {
            out += &point;
            if let Some(row) = extra.get(k) {
                for v in row {
                    out += &format!(",{v}");
                }
            }
            out.push('\n');
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const COLUMNS: TableColumns = TableColumns {
        names: ["x", "y"],
        row: "point",
        meaning: "x and y",
        number: "a number",
    };

    #[test]
    fn columns_are_found_by_name_and_other_columns_and_comments_are_skipped() {
        let text = "# made by hand\n\ny, note, x\n2, a, 1\n# between\n4,b,3\n";
        assert_eq!(
            COLUMNS.read(text).unwrap(),
            vec![(4, [1.0, 2.0]), (6, [3.0, 4.0])]
        );
    }

    #[test]
    fn a_bad_table_says_which_line_and_cell() {
        assert!(COLUMNS.read("# only\n").unwrap_err().contains("no header"));
        let e = COLUMNS.read("x,z\n1,2\n").unwrap_err();
        assert!(e.contains("no y column") && e.contains("x and y"), "{e}");
        let e = COLUMNS.read("x,y\n1,2\n1,inf\n").unwrap_err();
        assert_eq!(e, "line 3: y \"inf\" is not a number");
        let e = COLUMNS.read("x,y\n1\n").unwrap_err();
        assert_eq!(e, "line 2: y \"\" is not a number");
    }

    #[test]
    fn what_it_writes_it_reads_back() {
        let text = COLUMNS.write(
            &["from a test\nsecond line".into()],
            ["1,2".to_string(), "3,4".to_string()].into_iter(),
            &["note"],
            &[vec!["a".into()]],
        );
        assert_eq!(text, "# from a test\n# second line\nx,y,note\n1,2,a\n3,4\n");
        assert_eq!(
            COLUMNS.read(&text).unwrap(),
            vec![(4, [1.0, 2.0]), (5, [3.0, 4.0])]
        );
    }
}
