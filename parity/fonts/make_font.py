"""Makes ParityPlotSans.ttf, the font of `parity replay --plots`, from
DejaVu Sans 2.35 (e.g. matplotlib's mpl-data/fonts/ttf/DejaVuSans.ttf):

    python make_font.py DejaVuSans.ttf   # needs fontTools

- subset to printable ASCII and a few symbols, hinting and layout tables
  dropped (plotters' ab_glyph text uses outlines, advances and the legacy
  `kern` table only);
- each glyph's left side bearing moved out of the outline into the pair
  kerning: plotters 0.3.7 draws a glyph's ink at the pen position, ignoring
  the bearing, which spaces letters unevenly; with every bearing 0 and
  kern'(a, b) = kern(a, b) + lsb(b) the ink lands where the font puts it;
- renamed "Parity Plot Sans", as the Bitstream Vera and Arev licences ask
  of a modified font (LICENSE beside this file).
"""

import sys

from fontTools import subset
from fontTools.ttLib import TTFont, newTable
from fontTools.ttLib.tables._k_e_r_n import KernTable_format_0

SYMBOLS = "°–—−×↔→µ·±≥≤²³…"
# A format-0 kern subtable's length is 16 bits: at most ~10900 pairs.
PAIRS_PER_SUBTABLE = 9000


def main(source: str, target: str = "ParityPlotSans.ttf") -> None:
    font = TTFont(source)
    opts = subset.Options()
    opts.layout_features = []
    opts.hinting = False
    opts.name_IDs = ["*"]
    opts.notdef_outline = True
    opts.legacy_kern = True
    opts.drop_tables += ["FFTM", "GPOS", "GSUB", "GDEF", "MATH"]
    subsetter = subset.Subsetter(opts)
    subsetter.populate(unicodes=list(range(0x20, 0x7F)) + [ord(c) for c in SYMBOLS])
    subsetter.subset(font)

    glyf, hmtx = font["glyf"], font["hmtx"]
    kern_before = {}
    if "kern" in font:
        for table in font["kern"].kernTables:
            kern_before.update(table.kernTable)
    order = font.getGlyphOrder()
    lsb = {}
    for name in order:
        advance, bearing = hmtx[name]
        glyph = glyf[name]
        if glyph.numberOfContours == 0:
            lsb[name] = 0
            continue
        if glyph.isComposite():
            for component in glyph.components:
                component.x -= bearing
        else:
            glyph.coordinates.translate((-bearing, 0))
        glyph.recalcBounds(glyf)
        hmtx[name] = (advance - bearing, 0)
        lsb[name] = bearing

    mapped = sorted(set(font.getBestCmap().values()), key=order.index)
    pairs = {}
    for a in mapped:
        for b in mapped:
            value = kern_before.get((a, b), 0) + lsb[b]
            if value:
                pairs[(a, b)] = value
    kern = newTable("kern")
    kern.version = 0
    kern.kernTables = []

    def flush(table_pairs):
        table = KernTable_format_0()
        table.version, table.coverage, table.format = 0, 1, 0
        table.kernTable = table_pairs
        kern.kernTables.append(table)

    current, last_first = {}, None
    for (a, b), value in sorted(pairs.items(), key=lambda kv: (order.index(kv[0][0]), order.index(kv[0][1]))):
        # A first glyph's pairs stay in one subtable (the reader takes the
        # first subtable that has the pair).
        if len(current) >= PAIRS_PER_SUBTABLE and a != last_first:
            flush(current)
            current = {}
        current[(a, b)] = value
        last_first = a
    flush(current)
    font["kern"] = kern

    names = {
        1: "Parity Plot Sans",
        3: "Parity Plot Sans: modified subset of DejaVu Sans 2.35",
        4: "Parity Plot Sans",
        6: "ParityPlotSans",
        16: "Parity Plot Sans",
        18: "Parity Plot Sans",
    }
    for record in font["name"].names:
        if record.nameID in names:
            record.string = names[record.nameID]
    font["head"].flags |= 2  # left side bearing at x = 0
    font.save(target)


if __name__ == "__main__":
    main(*sys.argv[1:])
