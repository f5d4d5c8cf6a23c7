"""soft_rom.scale.fit, the former name of soft_rom.scale.streaming, still imports."""

from __future__ import annotations


def test_former_module_name_still_imports():
    import soft_rom.scale as scale
    from soft_rom.scale import fit as former
    from soft_rom.scale import streaming
    for name in former.__all__:
        assert getattr(former, name) is getattr(streaming, name)
    assert scale.fit_streaming is streaming.fit_streaming
