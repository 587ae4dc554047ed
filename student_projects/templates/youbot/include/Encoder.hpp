#ifndef ENCODER_HPP
#define ENCODER_HPP

// Turns the ico board's 14-bit wrapping counter into a continuous count from a chosen zero.
// A jump of more than half the range between two cycles is a wrap (the course convention:
// difference > 8192), which holds as long as a shaft turns less than 8192 counts per cycle.
class Encoder
{
public:
    static constexpr int range = 16384;

    void zero(int raw)
    {
        last_raw_ = raw;
        count_ = 0;
    }

    long update(int raw)
    {
        int diff = raw - last_raw_;
        if (diff > range / 2)
            diff -= range;
        else if (diff < -range / 2)
            diff += range;
        last_raw_ = raw;
        count_ += diff;
        return count_;
    }

    long count() const { return count_; }

private:
    int last_raw_ = 0;
    long count_ = 0;
};

#endif // ENCODER_HPP
