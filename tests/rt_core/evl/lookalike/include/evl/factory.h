/* EVL look-alike for CI, not libevl (see evl/evl.h): element creation flags. */
#ifndef XRF_EVL_LOOKALIKE_FACTORY_H
#define XRF_EVL_LOOKALIKE_FACTORY_H

#define EVL_CLONE_PRIVATE 0
#define EVL_CLONE_PUBLIC (1 << 16)
#define EVL_CLONE_OBSERVABLE (1 << 17)
#define EVL_CLONE_NONBLOCK (1 << 18)

#endif
