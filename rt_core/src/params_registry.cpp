// The runtime's parameter registry (params_registry.h): fixed arrays, filled before loop() by
// registrations (xrf/tunable.hpp; the file the build generates from a 20-sim export), read by
// the loop thread. Nothing here allocates.
#include "params_registry.h"

#include <cmath>
#include <cstdio>
#include <cstring>

#include "xrf/channels.h"
#include "xrf/tunable.hpp"

namespace xrf
{
namespace
{

struct Entry {
    xrf_param_desc desc;
    double *direct; // DECLARED: the Tunable's value
    uint32_t index; // 20SIM: m_P[index]
    bool tuned;     // a set wrote it: 20-sim's Initialize() must not undo it
    double value;   // the last value applied (or the default)
};

// A submodel whose m_P[] the 20-sim parameters address; its pointers are read at each apply,
// because 20-sim's generated constructor sets m_P after the base class registered the object.
struct Model {
    double **parameters;
    const int *count;
};

constexpr uint32_t kMaxModels = 4;

Entry g_entries[XRF_PARAMS_MAX];
uint32_t g_count = 0;
uint32_t g_origin = XRF_PARAMS_ORIGIN_NONE;
Model g_models[kMaxModels];
uint32_t g_models_n = 0;
// Registrations left out, reported at publish() (a constructor must not print: static init).
uint32_t g_dropped = 0;
char g_dropped_first[XRF_PARAM_NAME_MAX] = "";

void copyText(char *dst, size_t size, const char *src)
{
    std::snprintf(dst, size, "%s", src ? src : "");
}

bool nameOk(const char *name)
{
    if (name == nullptr || name[0] == '\0' || std::strlen(name) >= XRF_PARAM_NAME_MAX)
        return false;
    for (const char *c = name; *c; c++)
        if ((unsigned char)*c < 0x20 || (unsigned char)*c > 0x7e || *c == '"' || *c == '\'')
            return false;
    for (uint32_t i = 0; i < g_count; i++)
        if (std::strcmp(g_entries[i].desc.name, name) == 0)
            return false;
    return true;
}

Entry *add(const char *name)
{
    if (g_count >= XRF_PARAMS_MAX || !nameOk(name)) {
        if (g_dropped++ == 0)
            copyText(g_dropped_first, sizeof g_dropped_first, name);
        return nullptr;
    }
    Entry *e = &g_entries[g_count++];
    *e = Entry{};
    copyText(e->desc.name, sizeof e->desc.name, name);
    return e;
}

void write20sim(uint32_t index, double v)
{
    for (uint32_t m = 0; m < g_models_n; m++) {
        double *p = *g_models[m].parameters;
        if (p != nullptr && (int)index < *g_models[m].count)
            p[index] = v;
    }
}

void apply(Entry &e, double v)
{
    e.value = v;
    e.tuned = true;
    if (e.desc.source == XRF_PARAM_SOURCE_DECLARED)
        *e.direct = v;
    else
        write20sim(e.index, v);
}

} // namespace

void registerTunable(const char *name, double *value, double def, double min, double max,
                     const char *unit)
{
    if (value == nullptr || !std::isfinite(def) || !std::isfinite(min) || !std::isfinite(max) ||
        min > def || def > max) {
        if (g_dropped++ == 0)
            copyText(g_dropped_first, sizeof g_dropped_first, name);
        return;
    }
    Entry *e = add(name);
    if (e == nullptr)
        return;
    copyText(e->desc.unit, sizeof e->desc.unit, unit);
    e->desc.initial = def;
    e->desc.min = min;
    e->desc.max = max;
    e->desc.source = XRF_PARAM_SOURCE_DECLARED;
    e->desc.flags = XRF_PARAM_HAS_RANGE;
    e->direct = value;
    e->value = def;
}

void register20simTable(const char *const *names, const double *defaults, const char *const *units,
                        uint32_t count)
{
    g_origin = XRF_PARAMS_ORIGIN_20SIM;
    for (uint32_t i = 0; i < count; i++) {
        const double def = std::isfinite(defaults[i]) ? defaults[i] : 0.0;
        Entry *e = add(names[i]);
        if (e == nullptr)
            continue;
        copyText(e->desc.unit, sizeof e->desc.unit, units[i]);
        e->desc.initial = def;
        // No declared range: the host proposes one around the default, which a user may widen.
        e->desc.min = def;
        e->desc.max = def;
        e->desc.source = XRF_PARAM_SOURCE_20SIM;
        e->index = i;
        e->value = def;
    }
}

void register20simModel(double **parameters, const int *count)
{
    if (g_models_n < kMaxModels && parameters != nullptr && count != nullptr)
        g_models[g_models_n++] = Model{parameters, count};
}

namespace params
{

void publish(xrf_params *p, bool quiet)
{
    p->count = g_count;
    p->origin = g_origin;
    for (uint32_t i = 0; i < g_count; i++) {
        p->desc[i] = g_entries[i].desc;
        p->value[i] = g_entries[i].value;
    }
    if (g_dropped && !quiet)
        std::fprintf(stderr,
                     "xrf: %u tunable parameter(s) left out (first: '%s'): a name must be unique, "
                     "printable, shorter than %d characters, min <= default <= max, at most %d "
                     "parameters\n",
                     g_dropped, g_dropped_first, XRF_PARAM_NAME_MAX, XRF_PARAMS_MAX);
}

void take(xrf_params *p, uint32_t *seen, uint64_t cycle)
{
    xrf_param_set set; // on the loop's stack: ~800 bytes, prefaulted with the stack
    if (!xrf_params_take(p, seen, &set))
        return;
    const int rc = xrf_params_set_check(&set, g_count);
    if (rc == 0) {
        for (uint32_t i = 0; i < set.count; i++) {
            Entry &e = g_entries[set.index[i]];
            apply(e, set.value[i]);
            p->value[set.index[i]] = set.value[i];
        }
    }
    xrf_params_answer(p, set.seq, rc, cycle);
}

void afterInitialise()
{
    for (uint32_t i = 0; i < g_count; i++)
        if (g_entries[i].tuned && g_entries[i].desc.source == XRF_PARAM_SOURCE_20SIM)
            write20sim(g_entries[i].index, g_entries[i].value);
}

} // namespace params
} // namespace xrf
