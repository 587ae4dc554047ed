// Logs N doubles every cycle (N = $XRF_BENCH_NVARS, 1..64, default 32): d<i> = cycle + i / 64.
// The run() hook only fills the record, so a cycle's cost is the framework's plus this fill.
#include <cstdio>
#include <cstdlib>

#include "XenoFrtRosIco.hpp"

static constexpr int MAX_VARS = 64;

struct CostLog {
    double v[MAX_VARS];
};

static int nvars()
{
    const char *s = std::getenv("XRF_BENCH_NVARS");
    int n = s && *s ? std::atoi(s) : 32;
    return n < 1 ? 1 : n > MAX_VARS ? MAX_VARS : n;
}

class LoggerCost : public XenoFrtRosIco {
public:
    LoggerCost() : XenoFrtRosIco(1000, 100, 10, file, &record), file(true, "logs/cost", "xrf"), n_(nvars())
    {
        for (int i = 0; i < n_; i++) {
            std::snprintf(names_[i], sizeof names_[i], "d%d", i);
            logger.addVariable(names_[i], double_);
        }
    }

protected:
    int initialising() override
    {
        logger.initialise();
        logger.start();
        fill();
        return 1;
    }
    int initialised() override { fill(); return 0; }
    int run() override { fill(); return 0; }
    int stopping() override { fill(); return 1; }
    int stopped() override { fill(); return 0; }
    int paused() override { fill(); return 0; }

private:
    void fill()
    {
        const double c = (double)getCyclesCount();
        for (int i = 0; i < n_; i++)
            record.v[i] = c + i / 64.0;
        xeno_msg.cycle = (int64_t)getCyclesCount();
        xeno_msg.d0 = record.v[0];
    }

    XenoFileHandler file;
    CostLog record{};
    int n_;
    char names_[MAX_VARS][8];
};

int main()
{
    static LoggerCost bench;
    return bench.loop() == 0 ? 0 : 1;
}
