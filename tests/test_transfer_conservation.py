"""What each transfer scheme declares it conserves holds (mpmlab.testing.check_conservation: a
spinning, drifting block, no gravity, 40 fp64 steps), and the check fails where a scheme does not
conserve (PIC loses the angular momentum that APIC's C carries; Jiang et al. 2015 Sec. 5.3)."""
import pytest

from mpmlab.testing import ConformanceError, check_conservation
from mpmlab.transfers import BUILTIN


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_builtin_schemes_conserve_what_they_declare_jax(name):
    r = check_conservation(name, 2, "jax")
    assert r["drift"]["linear_momentum"] <= 1e-11


@pytest.mark.parametrize("name", ["apic", "mls"])
def test_affine_schemes_conserve_angular_momentum_on_warp(name):
    r = check_conservation(name, 2, "warp")
    assert r["declared"] == ["angular_momentum", "linear_momentum"]
    assert r["drift"]["angular_momentum"] <= 1e-11


def test_the_check_fails_where_angular_momentum_is_not_conserved():
    with pytest.raises(ConformanceError, match=r"transfer 'pic' 2D jax fp64, 40 steps: angular momentum drifts "
                                               r"by [0-9.e-]+ \(relative\) > tolerance 1e-11"):
        check_conservation("pic", 2, "jax", quantities=("angular_momentum",))
