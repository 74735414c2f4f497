"""Where the data that ships inside the package lives: the particle catalogue, the optical
constants, the example recipes and the JSON Schemas (package data, so a built wheel has them).

The repository's top-level ``catalog`` and ``schemas`` are links to these folders.

>>> (CATALOG_DIR / "particles.yaml").is_file(), (SCHEMAS_DIR / "recipe.schema.json").is_file()
(True, True)
>>> "tri-coat-pearl-white.yaml" in {p.name for p in RECIPES_DIR.glob("*.yaml")}
True
"""

from pathlib import Path

#: The installed package's folder.
PACKAGE_DIR = Path(__file__).resolve().parent
#: Particle catalogue (``particles.yaml``), optical constants (``materials/``), example recipes.
CATALOG_DIR = PACKAGE_DIR / "catalog"
MATERIALS_DIR = CATALOG_DIR / "materials"
RECIPES_DIR = CATALOG_DIR / "recipes"
#: JSON Schemas of the catalogue, the recipes and the store metadata.
SCHEMAS_DIR = PACKAGE_DIR / "schemas"
