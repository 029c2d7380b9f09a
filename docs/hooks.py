"""MkDocs hook: the committed result figures (``benchmarks/results/**/*.png``) join the site at
the same paths, so the results pages show the figures the benchmarks wrote, not copies."""
from pathlib import Path

from mkdocs.structure.files import File


def on_files(files, config):
    root = Path(config["config_file_path"]).parent
    for png in sorted((root / "benchmarks" / "results").rglob("*.png")):
        files.append(File(png.relative_to(root).as_posix(), str(root), config["site_dir"], config["use_directory_urls"]))
    return files
