"""Outputs are never lost: atomic writes, every output checked before any work, one clean
message per refusal, and a warning when calibrate finds no brighter-fatter."""

import json

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from bfpsf.cli import main
from bfpsf.errors import BFPSFFileExistsError, BFPSFInputError
from bfpsf.files import check_outputs
from bfpsf.outputs import save_figure, write_fits, write_json, write_table


def _fail_half_way(path, payload=b"SIMPLE  =                    T"):
    """Write the start of a file, then fail as a full disk does."""
    with open(path, "wb") as stream:
        stream.write(payload)
    raise OSError(28, "No space left on device")


def test_failing_fits_write_leaves_the_old_product_byte_identical(tmp_path, monkeypatch):
    path = tmp_path / "calib.fits"
    write_fits(fits.HDUList([fits.PrimaryHDU(np.arange(12.0).reshape(3, 4))]), path)
    before = path.read_bytes()
    monkeypatch.setattr(fits.HDUList, "writeto",
                        lambda self, name, *args, **kwargs: _fail_half_way(name))
    with pytest.raises(OSError, match="No space left on device"):
        write_fits(fits.HDUList([fits.PrimaryHDU(np.zeros((3, 4)))]), path, overwrite=True)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib.fits"]  # no partial file left


def test_failing_table_json_and_figure_writes_leave_the_old_files(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    table_path, json_path, png_path = tmp_path / "t.ecsv", tmp_path / "s.json", tmp_path / "f.png"
    write_table(Table({"x": [1.0, 2.0]}), table_path)
    write_json(json_path, {"a": 1})
    save_figure(plt.figure(), png_path)
    before = {path: path.read_bytes() for path in (table_path, json_path, png_path)}

    monkeypatch.setattr(Table, "write", lambda self, name, **kwargs: _fail_half_way(name))
    with pytest.raises(OSError):
        write_table(Table({"x": [3.0]}), table_path, overwrite=True)
    monkeypatch.setattr(json, "dumps", lambda *args, **kwargs: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        write_json(json_path, {"a": 2}, overwrite=True)
    figure = plt.figure()
    monkeypatch.setattr(figure, "savefig", lambda name, **kwargs: _fail_half_way(name))
    with pytest.raises(OSError):
        save_figure(figure, png_path, overwrite=True)
    for path, content in before.items():
        assert path.read_bytes() == content, path
    assert len(list(tmp_path.iterdir())) == 3


def test_check_outputs_refuses_before_any_work(tmp_path):
    free = tmp_path / "a.fits"
    with pytest.raises(BFPSFInputError) as error:
        check_outputs([free, tmp_path / "." / "a.fits"], False)
    assert str(error.value) == (f"{free} and {tmp_path / '.' / 'a.fits'} are the same file: "
                                "give each output its own path")
    missing = tmp_path / "nosuch" / "b.json"
    with pytest.raises(BFPSFInputError) as error:
        check_outputs([free, missing], False)
    assert str(error.value) == f"cannot write {missing}: directory {missing.parent} does not exist"
    with pytest.raises(BFPSFInputError) as error:
        check_outputs([tmp_path], False)
    assert str(error.value) == f"output {tmp_path} is a directory"
    free.write_text("x")
    with pytest.raises(BFPSFFileExistsError) as error:
        check_outputs([free], False)
    assert str(error.value) == f"{free} exists; pass --overwrite to replace it"
    check_outputs([free, None], True)
    # files inside an output directory the command will create
    check_outputs([tmp_path / "report" / "report.md"], False, directories=[tmp_path / "report"])
    with pytest.raises(BFPSFInputError) as error:
        check_outputs([], False, directories=[free])
    assert str(error.value) == f"output directory {free} is a file"


@pytest.mark.parametrize("command", ["calibrate", "measure", "photometry"])
def test_cli_refuses_the_same_path_for_two_outputs(tmp_path, capsys, command):
    out = tmp_path / "out"
    extra = {"calibrate": [], "measure": [], "photometry": ["--psf", str(tmp_path / "p.fits")]}
    code = main([command, str(tmp_path / "nosuch.fits"), *extra[command], "-o", str(out),
                 "--json", str(out)])
    assert code == 1
    assert capsys.readouterr().err == (f"bfpsf {command}: error: {out} and {out} are the same "
                                       "file: give each output its own path\n")
    assert not out.exists()


def test_cli_checks_the_json_directory_before_the_work(tmp_path, capsys):
    out, json_path = tmp_path / "c.fits", tmp_path / "nosuch" / "c.json"
    assert main(["calibrate", str(tmp_path / "nosuch.fits"), "-o", str(out),
                 "--json", str(json_path)]) == 1
    assert capsys.readouterr().err == (f"bfpsf calibrate: error: cannot write {json_path}: "
                                       f"directory {json_path.parent} does not exist\n")
    assert not out.exists()


def test_calibrate_warns_when_the_flats_show_no_brighter_fatter(tmp_path, capsys):
    """Poisson flats without any pixel correlation: a(0, 0) is not negative, no shifts."""
    rng = np.random.default_rng(5)
    paths = []
    for level, exptime in ((2e3, 1.0), (1e4, 5.0), (3e4, 15.0), (6e4, 30.0), (9e4, 45.0)):
        for member in (1, 2):
            path = tmp_path / f"flat_{int(exptime)}_{member}.fits"
            header = fits.Header({"EXPTIME": exptime})
            image = rng.poisson(level, (64, 64)) / 1.5
            fits.PrimaryHDU(image.astype(np.float32), header=header).writeto(path)
            paths.append(str(path))
    out, json_path = tmp_path / "c.fits", tmp_path / "c.json"
    code = main(["calibrate", *paths, "-o", str(out), "--json", str(json_path), "--maxlag", "2",
                 "--n-monte-carlo", "0"])
    assert code == 0
    summary = json.loads(json_path.read_text())
    warnings = [w for w in summary["warnings"] if w.startswith("no measurable brighter-fatter")]
    assert len(warnings) == 1
    err = capsys.readouterr().err
    assert f"WARNING: {warnings[0]}\n" in err
    # five pairs: too few for the full PTC model, and said so
    assert ("WARNING: the full PTC model is under-constrained by 5 flat pairs (gain, read noise "
            "and a can be biased); give at least 8 pairs over the flux range or use --model "
            "exponential\n") in err


def test_tables_carry_units_on_errors_schema_and_version_and_no_object_reprs(tmp_path):
    import astropy.units as u

    from bfpsf import __version__
    from bfpsf.outputs import TABLE_SCHEMA_VERSION

    table = Table({"sigma_x": [1.0] * u.pix, "sigma_x_err": [0.1], "flux_e": [5.0] * u.electron,
                   "flux_e_err": [0.5]})
    table.meta.update({"gains": [np.float64(1.7)], "threshold": 5.0, "saturation_e": None,
                       "solution": object()})
    write_table(table, tmp_path / "t.ecsv")
    text = (tmp_path / "t.ecsv").read_text()
    assert "object at 0x" not in text
    back = Table.read(tmp_path / "t.ecsv")
    assert back["sigma_x_err"].unit == u.pix and back["flux_e_err"].unit == u.electron
    assert back.meta == {"gains": [1.7], "threshold": 5.0, "saturation_e": None,
                         "bfpsf_schema": TABLE_SCHEMA_VERSION, "bfpsf_version": __version__}
    assert "sigma_x_err" in table.colnames and table["sigma_x_err"].unit is None  # not modified
