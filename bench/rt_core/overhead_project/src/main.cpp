// Overhead benchmark controller: XenoFrtRosIco at 1 kHz (XRF_FREQ overrides), Xeno2Ros published
// at 100 Hz, monitor at 30 Hz, a 16-double XenoFrtLogger record every cycle. The run() hook does
// nothing but the monitor print, so that everything else a cycle costs is the framework's.
#include "XenoFrtRosIco.hpp"

struct BenchLog {
    double v[16];
};

class OverheadBench : public XenoFrtRosIco {
public:
    OverheadBench() : XenoFrtRosIco(1000, 100, 30, file, &record), file(false, "overhead_bench", "csv")
    {
        static const char *names[16] = {"d0", "d1", "d2",  "d3",  "d4",  "d5",  "d6",  "d7",
                                        "d8", "d9", "d10", "d11", "d12", "d13", "d14", "d15"};
        for (int i = 0; i < 16; i++) {
            record.v[i] = 0.5 * i;
            logger.addVariable(names[i], double_);
        }
    }

protected:
    int initialising() override
    {
        logger.initialise();
        logger.start();
        return 1;
    }
    int run() override
    {
        monitor.printf("bench %lu\n", getCyclesCount());
        return 0;
    }

private:
    XenoFileHandler file;
    BenchLog record{};
};

int main()
{
    static OverheadBench bench;
    return bench.loop() == 0 ? 0 : 1;
}
