"""Physical bounds of the numbers a job config or a command-line option may set.

Every config field that comes from outside has a type from here, so that a value no survey
needs (a 1 mm free-space voxel, a 1e9 px mask pad, 1e6 threads, a 1e308 m range) is refused
where it enters, as one line naming the field, instead of exhausting memory or overflowing
deep inside a pipeline. NaN and infinity are refused by every float type. Fields keep their
own lower bounds (`gt=0`, `ge=2`, ...) beside these types; the bounds here are the outer ones a
demanding mapping engineer would still find sensible.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from app.core.limits import INT64_MAX

MAX_RANGE_M = 1000.0  # no mobile-mapping sensor sees farther
MAX_COUNT = 1_000_000  # frames, points, samples, steps of one run
MAX_THREADS = 256
MAX_PIXELS = 200
GAMMA_RANGE = (0.2, 2.0)  # an image's tone curve: past these, shadows or lights turn flat

# Where a type has a bound, it wins over a field's own bound of the same kind (pydantic merges
# the annotation last): types here bound one side where fields need their own other side.

# metres: a grid or voxel edge (free-space voxels, ground cells, clustering voxels, pillars)
Resolution = Annotated[float, Field(ge=0.02, le=5.0, allow_inf_nan=False)]
# metres: a distance, range, radius, gap or height (the field sets its lower bound)
Metres = Annotated[float, Field(le=MAX_RANGE_M, allow_inf_nan=False)]
# metres at the scale of one object: inflations, tolerances, halos (the field's lower bound)
ObjectMetres = Annotated[float, Field(le=10.0, allow_inf_nan=False)]
# pixels of a camera image (mask pads)
Pixels = Annotated[int, Field(ge=0, le=MAX_PIXELS)]
# the gamma of an image's tone curve (below 1 lifts the dark tones)
Gamma = Annotated[float, Field(ge=GAMMA_RANGE[0], le=GAMMA_RANGE[1], allow_inf_nan=False)]
# a number of things: frames, points, samples, slices (the field sets its lower bound)
Count = Annotated[int, Field(le=MAX_COUNT)]
# training epochs (the field sets its lower bound)
Epochs = Annotated[int, Field(le=10_000)]
# worker threads; 0 = all cores
Threads = Annotated[int, Field(ge=0, le=MAX_THREADS)]
# a share or probability, 0..1 (a field may exclude the ends with gt / lt)
Share = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]
# metres per second
Speed = Annotated[float, Field(ge=0.0, le=100.0, allow_inf_nan=False)]
# seconds of wall-clock time (a training time limit): at most a week
Seconds = Annotated[float, Field(gt=0.0, le=7 * 24 * 3600.0, allow_inf_nan=False)]
# a learning rate, weight decay or momentum
Rate = Annotated[float, Field(le=1.0, allow_inf_nan=False)]
# a random seed
Seed = Annotated[int, Field(ge=0, le=2**32 - 1)]
# a store id (survey, model version)
RecordId = Annotated[int, Field(ge=1, le=INT64_MAX)]
