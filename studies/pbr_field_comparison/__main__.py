"""``python -m studies.pbr_field_comparison``: the light-field study (``study.main``)."""

from .study import main


if __name__ == "__main__":
    main()
