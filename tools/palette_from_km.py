"""Print the catalogue entries of the tinters described by flakedb/catalog/tinters/palette.yaml.

    PYTHONPATH=$PWD python tools/palette_from_km.py > /tmp/entries.yaml   # then paste into particles.yaml

The numbers come from flakedb.paint.km_palette (tests/paint/test_palette.py checks that the catalogue
holds exactly these); this script only formats them.
"""

import sys

import yaml

from flakedb.paint.catalog import load_catalog
from flakedb.paint.km_palette import PALETTE_FILE, palette_tables


def fmt(values):
    return "[" + ", ".join(f"{float(v):.6g}" for v in values) + "]"


def main():
    pal = yaml.safe_load(PALETTE_FILE.read_text(encoding="utf-8"))
    tables = palette_tables(pal, load_catalog(None), PALETTE_FILE.parent)
    ref = pal["reference"]
    out = []
    for name, sp in pal["species"].items():
        t = tables[name]
        how = (f"catalog/tinters/{pal['table']} column {sp['column']} (relative K, S) x the absolute S of "
               f"{ref['species']} at volume fraction {ref['volume_fraction']['value']:g} (palette.yaml), "
               f"{pal.get('conversion', {}).get('value', 'Star1988')} KM->RT with g {sp['asymmetry_g']['value']:g}, / pigment volume fraction "
               f"{sp['pigment_volume_fraction']['value']:g} (an assumption, palette.yaml); {pal['extend_to_nm']} nm "
               f"end: last band held (palette.yaml)")
        out += [f"  {name}:", "    kind: tinter", f"    description: >-\n      {sp['description'].strip()}",
                f"    colour_index: {sp['colour_index']}",
                "    source: >-\n      RIT Artist Paint Spectral Database (two-constant KM of "
                "Golden Heavy Body acrylics), as redistributed in Unicolour (MIT), catalog/tinters/README.md; "
                "converted by flakedb/paint/km_palette.py with catalog/tinters/palette.yaml"]
        if "density_g_cm3" in sp:
            out += ["    density_g_cm3:", f"      value: {sp['density_g_cm3']['value']}",
                    f"      source: >-\n        {' '.join(sp['density_g_cm3']['source'].split())}"]
        for key, arr in (("specific_absorption_per_um", t["sigma_a_per_um"]),
                         ("specific_scattering_per_um", t["sigma_s_per_um"])):
            out += [f"    {key}:", f"      wavelength_nm: {fmt(t['wavelength_nm'])}", f"      value: {fmt(arr)}",
                    f"      source: >-\n        {how}"]
        out += ["    asymmetry_g:", f"      value: {sp['asymmetry_g']['value']}",
                "      source: assumption, catalog/tinters/palette.yaml", ""]
    sys.stdout.write("\n".join(out))


if __name__ == "__main__":
    main()
