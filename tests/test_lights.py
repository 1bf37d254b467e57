import numpy as np
import pytest

import jaxps


def test_lights_from_angles_yale_convention():
    l = jaxps.lights_from_angles([0, 90, 0, 35], [0, 0, 90, 15])
    np.testing.assert_allclose(l[0], [0, 0, 1], atol=1e-7)
    np.testing.assert_allclose(l[1], [-1, 0, 0], atol=1e-7)  # +azimuth lights the image's left
    np.testing.assert_allclose(l[2], [0, 1, 0], atol=1e-7)  # +elevation lights from above
    a, e = np.radians(35), np.radians(15)
    np.testing.assert_allclose(l[3], [-np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)],
                               rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(l, axis=1), 1, rtol=1e-6)
    assert l.dtype == np.float32


def test_parse_yale_name():
    assert jaxps.parse_yale_name("yaleB01_P00A+035E+15.pgm") == (35.0, 15.0)
    assert jaxps.parse_yale_name("/x/yaleB02_P00A-110E-20.pgm") == (-110.0, -20.0)
    assert jaxps.parse_yale_name("yaleB01_P00_Ambient.pgm") is None
    assert jaxps.parse_yale_name("cat.0.png") is None
    # a rig's own frames named the same way, without Yale B's pose
    assert jaxps.parse_yale_name("A+035E+15.png") == (35.0, 15.0)
    assert jaxps.parse_yale_name("face_A-25E+20.tif") == (-25.0, 20.0)
    assert jaxps.parse_yale_name("P00A+0E-20.pgm") == (0.0, -20.0)
    assert jaxps.parse_yale_name("dataA+035E+15.png") is None  # not a name's own part
    assert jaxps.parse_yale_name("yaleB01_P00A+035E+15.pgm.bak") is None


def test_load_lights_normalises(tmp_path):
    f = tmp_path / "lights.txt"
    f.write_text("3\n2 0 2\n0 0 3\n0 1 1\n")
    l = jaxps.load_lights(f)
    np.testing.assert_allclose(l[0], [2**-0.5, 0, 2**-0.5], rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(l, axis=1), 1, rtol=1e-6)
    f.write_text("0 0 1\n1 0 1\n0 1 1\n")  # no count line
    assert jaxps.load_lights(f).shape == (3, 3)


def test_load_shared_psm_lights(data):
    l = jaxps.load_lights(data / "psm" / "lights.txt")
    assert l.shape == (12, 3)
    assert np.all(l[:, 2] > 0.7)  # all lights in front, z toward the viewer


def test_load_lights_reads_what_spreadsheets_and_notepad_write(tmp_path):
    # a byte-order mark and CRLF line ends (Windows Notepad), tabs and semicolons (CSV exports)
    f = tmp_path / "lights.txt"
    f.write_bytes(b"\xef\xbb\xbf3\r\n0\t0\t1\r\n0.6;0;0.8\r\n0, 0.6, 0.8\r\n")
    np.testing.assert_allclose(jaxps.load_lights(f), [[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8]],
                               atol=1e-7)
    f.write_text("0,6;0;0,8\n0;0;1\n0;0,6;0,8\n")  # decimal commas: an error, not a misread
    with pytest.raises(ValueError, match="3 numbers per line"):
        jaxps.load_lights(f)


@pytest.mark.parametrize(
    "text, match",
    [
        ("4\n0 0 1\n1 0 1\n0 1 1\n", "header says 4"),
        ("0 0 1\n1 0\n", r"3 numbers per line \(x y z\), got \['1', '0'\]$"),
        # azimuth and elevation, as a rig's drawing gives them: the error says how to convert
        ("0 0\n25 0\n-25 0\n", r"look like angles: .*jaxps.lights_from_angles"),
        ("0 0 1\n1 0 x\n0 1 1\n", "cannot parse"),
        ("0 0 1\n1 0 1\n", "at least 3"),
        ("0 0 1\n1 0 1\n2 0 2\n", "condition number"),
        ("0 0 1\n0 0 0\n0 1 1\n", "zero vectors"),
    ],
)
def test_load_lights_errors_name_the_file(tmp_path, text, match):
    f = tmp_path / "bad_lights.txt"
    f.write_text(text)
    with pytest.raises(ValueError, match=match) as err:
        jaxps.load_lights(f)
    assert "bad_lights.txt" in str(err.value)


def test_missing_lights_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.txt"):
        jaxps.load_lights(tmp_path / "nothere.txt")
    (tmp_path / "image.png").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")  # an image by mistake
    with pytest.raises(ValueError, match="image.png: not a text file"):
        jaxps.load_lights(tmp_path / "image.png")


def test_validate_lights_errors():
    with pytest.raises(ValueError, match=r"\(K, 3\)"):
        jaxps.validate_lights(np.ones((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        jaxps.validate_lights([[0, 0, 1], [1, 0, 1], [np.nan, 1, 1]])
    with pytest.raises(ValueError, match="same length"):
        jaxps.lights_from_angles([0, 1], [0])
